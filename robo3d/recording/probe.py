"""A cheap summary of a recording that never raises (:func:`probe_recording`).

The workflow probes every recording of a batch while it builds its DAG, so a probe reads
no message: it uses the MCAP summary section (statistics, channels, attachment and
metadata indexes; https://mcap.dev/spec) when the file has an intact one
(:func:`~robo3d.recording.framing.read_summary`), and a record-by-record scan that keeps
no message otherwise (:func:`~robo3d.recording.framing.scan_file`). It says whether the
role topics carry a supported schema (:func:`~robo3d.recording.decoding.allowed_schemas`)
and whether there are images (``recording-format.md``, Topics).
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field

from ..errors import RecordingError
from .decoding import allowed_schemas, ros_type
from .framing import bag_files, read_summary, scan_file
from .model import DEFAULT_TOPICS, TopicMap

__all__ = ["RecordingSummary", "probe_recording"]


@dataclass
class RecordingSummary:
    """What :func:`probe_recording` learnt about a recording without reading it all.

    Attributes
    ----------
    path : str
    readable : bool
        False when the file cannot be used at all (then ``problem`` says why).
    problem : str or None
        Why it is unreadable, or a warning about a readable file (e.g. truncated).
    n_views, n_laser_frames, n_calibrations, n_tf : int
        Messages on the views, laser, calibration and tf (+ tf_static) topics.
    has_ground_truth : bool
        Some attachment's name starts with ``ground_truth/``.
    kind : str or None
        ``kind`` of the ``robo3d.recording`` metadata (``scan`` or ``calibration``).
    metadata : dict
        Every metadata record, name to dict.
    topics : dict
        Topic to ``(schema name, message encoding, message count)``.
    attachments : list of str
        Attachment names.
    files : list of str
        The MCAP files (several for a split rosbag2 directory).
    """

    path: str
    readable: bool
    problem: str | None = None
    n_views: int = 0
    n_laser_frames: int = 0
    n_calibrations: int = 0
    n_tf: int = 0
    has_ground_truth: bool = False
    kind: str | None = None
    metadata: dict[str, dict[str, str]] = field(default_factory=dict)
    topics: dict[str, tuple[str, str, int]] = field(default_factory=dict)
    attachments: list[str] = field(default_factory=list)
    files: list[str] = field(default_factory=list)


def probe_recording(path: str | os.PathLike[str],
                    topics: TopicMap = DEFAULT_TOPICS) -> RecordingSummary:
    """Summarise a recording cheaply; never raises.

    Uses the MCAP summary section (statistics, channels, attachment and metadata indexes)
    when the file has an intact one, and a record-by-record scan (no message decoding)
    otherwise.

    Parameters
    ----------
    path : str or path-like
    topics : TopicMap

    Returns
    -------
    RecordingSummary
        ``readable=False`` with ``problem`` set for a file that is missing, not MCAP,
        carries an unsupported schema or encoding on a role topic, or has no images.
    """
    spath = os.fspath(path)
    try:
        return _probe(spath, topics)
    except Exception as exc:  # the contract: one bad file must not stop a batch
        reason = str(exc) if isinstance(exc, RecordingError) else \
            f"{spath}: {type(exc).__name__}: {exc}"
        return RecordingSummary(path=spath, readable=False, problem=reason)


def _probe(path: str, topics: TopicMap) -> RecordingSummary:
    if not os.path.exists(path):
        return RecordingSummary(path=path, readable=False, problem=f"{path}: no such file")
    files, file_warnings = bag_files(path)
    scans = []
    for f in files:
        scan = None
        try:
            scan = read_summary(f)
        except Exception:  # damaged summary: scan instead
            scan = None
        if scan is None:
            scan = scan_file(f, lambda _t: False, keep_attachment_data=False)
        scans.append(scan)
    by_topic: dict[str, tuple[str, str, int]] = {}
    attachments: set[str] = set()
    metadata: dict[str, dict[str, str]] = {}
    for scan in scans:
        for cid, ch in scan.channels.items():
            sch = scan.schemas.get(ch.schema_id)
            name = sch.name if sch is not None else ""
            n = scan.counts.get(cid, 0)
            old = by_topic.get(ch.topic)
            by_topic[ch.topic] = (name, ch.message_encoding, n + (old[2] if old else 0))
        attachments.update(scan.attachments)
        for name, md in scan.metadata.items():
            metadata.setdefault(name, {}).update(md)

    def count(t: str) -> int:
        return by_topic.get(t, ("", "", 0))[2]

    summary = RecordingSummary(
        path=path, readable=True,
        n_views=count(topics.views), n_laser_frames=count(topics.laser),
        n_calibrations=count(topics.calibration),
        n_tf=count(topics.tf) + count(topics.tf_static),
        has_ground_truth=any(a.startswith("ground_truth/") for a in attachments),
        kind=metadata.get("robo3d.recording", {}).get("kind"),
        metadata=metadata, topics=by_topic, attachments=sorted(attachments), files=files)
    problems = []
    expect = {topics.tf: "tf", topics.tf_static: "tf", topics.calibration: "calibration",
              topics.views: "image", topics.laser: "image"}
    for topic, role in expect.items():
        if topic not in by_topic or by_topic[topic][2] == 0:
            continue
        name, enc, _ = by_topic[topic]
        ok = ((enc == "protobuf" and name in allowed_schemas("protobuf", role))
              or (enc == "json" and (name in allowed_schemas("json", role) or name == ""))
              or (enc == "cdr" and ros_type(name) in allowed_schemas("ros2", role)))
        if not ok:
            every = allowed_schemas("protobuf", role) + allowed_schemas("ros2", role)
            problems.append(f"topic {topic} carries {name or '(no schema)'!r} encoded as "
                            f"{enc!r}; supported: {' or '.join(every)} (Foxglove schemas as "
                            f"protobuf or json, ROS 2 types as cdr)")
    if problems:
        summary.readable = False
        summary.problem = f"{path}: " + "; ".join(problems)
        return summary
    truncated = [s.truncated for s in scans if s.truncated]
    if summary.n_views == 0 and summary.n_laser_frames == 0:
        summary.readable = False
        present = sorted(t for t, v in by_topic.items() if v[2])
        summary.problem = (f"{path}: no images on {topics.views} or {topics.laser} (topics "
                           f"with messages: {', '.join(present) or 'none'})"
                           + (f" ({'; '.join(truncated)})" if truncated else ""))
        return summary
    warnings = file_warnings + [w for s in scans for w in s.warnings]
    if warnings:
        summary.problem = f"{path}: " + "; ".join(warnings)
    return summary
