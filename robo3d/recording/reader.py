"""Reading recordings (``recording-format.md``) into a :class:`~.model.Recording`.

:func:`read_recording` reads any MCAP recording that follows the contract, whoever wrote
it: robo3d's simulator, a converter, or a real cell's ROS 2 bag (a bare ``.mcap`` or a
rosbag2 directory). This module assembles the recording and checks it; the work is split
by concern:

- :mod:`~robo3d.recording.framing`: the files of a recording, MCAP record framing, and
  where a damaged file breaks (truncation, corrupt chunks: read what is intact, say what
  was lost);
- :mod:`~robo3d.recording.decoding`: message decoding (Foxglove protobuf/JSON and ROS 2
  CDR) into transform samples, calibrations, images and stamps;
- this module: which topic plays which role, the frame map, building the
  :class:`~robo3d.transforms.TransformBuffer` and the image lists, the topic statistics,
  and the checks whose errors name the file, topic, frame and time.

The other entry points are re-exported here: :func:`probe_recording` summarises a
recording cheaply and never raises (:mod:`~robo3d.recording.probe`; the workflow calls it
for every recording of a batch while it builds the DAG); :func:`bag_files` lists the MCAP
files of a recording; :func:`read_ground_truth_tf` reads a recording's true ``base ->
flange`` samples (:mod:`~robo3d.recording.ground_truth`); :func:`chain_problem` says why a
frame cannot be expressed in another.

Choices
-------
- ``frames`` maps roles to recorded frame names (the config's ``frames`` section, e.g.
  ``{"base": "base_link", "flange": "tool0", "camera": "camera_color_optical_frame",
  "laser": "laser_link"}``). The recorded names are renamed to the roles in the
  transform tree, in images' ``frame_id`` and in calibrations, so the pipeline sees only
  roles. A recording that uses the role names themselves reads unchanged with the same
  map (one config serves a batch of ROS bags and native recordings); one that has both
  a role's recorded name and the role's own name is an error (which one is meant is
  ambiguous).
- Other topics than the role topics are skipped unread (their counts and log times are
  kept in :attr:`Recording.topics`).
- Transforms: non-finite values, or a quaternion whose norm is off by more than 1e-3,
  are errors naming topic, link and time; a smaller deviation is renormalised.
  Timestamps out of order on a link are sorted with a warning; duplicated stamps keep
  the last sample (with a warning when the values differ). A static link published
  several times with different values keeps the first, with a warning.
- Images are kept encoded. Out-of-order timestamps on an image topic are sorted with a
  warning; an exact duplicate (same topic, frame_id and stamp) keeps the last one.
- ``require=True`` checks completeness: each requested role has messages; when there
  are images, a calibration for each image's ``frame_id`` and a transform chain from
  ``base_frame`` to it (the chain's structure only: whether a pose exists at each
  image's time is checked by :meth:`Recording.camera_poses`). ``require=False`` skips
  these checks (damaged or non-finite data are errors either way). A missing role in a
  truncated or damaged file says so.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Iterable, Mapping

import numpy as np

from ..errors import CalibrationError, RecordingError, TransformError
from ..transforms import TransformBuffer
from .decoding import QUAT_TOL, MessageDecoder, decode_scan
from .framing import Scan, bag_files, scan_file
from .ground_truth import GROUND_TRUTH_TF, read_ground_truth_tf
from .model import (
    DEFAULT_TOPICS,
    FRAME_ROLES,
    ImageMessage,
    JointStates,
    Recording,
    TopicMap,
    TopicStats,
)
from .probe import RecordingSummary, probe_recording

__all__ = [
    "RecordingSummary",
    "read_recording",
    "probe_recording",
    "bag_files",
    "read_ground_truth_tf",
    "chain_problem",
    "GROUND_TRUTH_TF",
    "STAMP_SOURCES",
]

_log = logging.getLogger(__name__)

#: Where a message's time comes from: its own stamp, or the MCAP log time.
STAMP_SOURCES = ("header", "log_time")
_ROLES = ("views", "laser")


# =========================================================================== reading
def read_recording(path: str | os.PathLike[str], *, topics: TopicMap = DEFAULT_TOPICS,
                   roles: Iterable[str] = ("views", "laser"),
                   max_pose_gap_ns: int = 50_000_000, base_frame: str = "base",
                   require: bool = True, frames: Mapping[str, str] | None = None,
                   stamp_source: str = "header", image_offset_ns: int = 0,
                   joint_states: bool = False) -> Recording:
    """Read a recording into memory, images still encoded.

    Parameters
    ----------
    path : str or path-like
        An MCAP file following ``recording-format.md`` (Foxglove schemas or ROS 2 CDR),
        or a rosbag2 directory.
    topics : TopicMap
        Which topic carries which role.
    roles : iterable of {"views", "laser"}
        Image roles to load. Calibration and transforms are always read.
    max_pose_gap_ns : int
        Widest gap between two pose samples to interpolate across, nanoseconds (the
        config's ``max_pose_gap``), given to the :class:`TransformBuffer`.
    base_frame : str
        The fixed frame poses are expressed in, as the pipeline names it (after
        ``frames`` renamed the recorded names to roles).
    require : bool
        Check completeness (see the module docstring): every requested role has
        messages, every image a calibration and a transform chain to ``base_frame``.
    frames : mapping of role -> recorded frame name, optional
        Roles among ``base``, ``flange``, ``camera``, ``laser`` (the config's
        ``frames``); recorded names are renamed to the roles.
    stamp_source : {"header", "log_time"}
        A message's time: its own stamp (the contract) or its MCAP log time.
    image_offset_ns : int
        Added to every image's time (views and laser frames), nanoseconds.
    joint_states : bool
        Also read ``sensor_msgs/msg/JointState`` on ``topics.joint_states`` into
        :attr:`Recording.joint_states` (informational; a problem there is a warning).

    Returns
    -------
    Recording
        With ``warnings`` listing everything accepted but suspicious (truncation, skipped
        chunks, sorted timestamps, ...); each is also logged.

    Raises
    ------
    RecordingError
        Not an MCAP file, unsupported schema/encoding on a role topic, undecodable message,
        a required role without messages (saying so when the file is truncated).
    TransformError
        Non-finite or non-unit transforms, a chain from ``base_frame`` to an image's
        frame that does not connect, no transforms at all, an ambiguous frame name.
    CalibrationError
        Missing, unsupported or non-finite calibration.
    ImageDecodeError
        A raw image encoding that is not supported.
    ValueError
        Bad arguments (roles, frames, stamp_source, max_pose_gap_ns).
    """
    spath = os.fspath(path)
    roles = _check_roles(roles)
    if max_pose_gap_ns <= 0:
        raise ValueError(f"max_pose_gap_ns must be positive, got {max_pose_gap_ns}")
    if stamp_source not in STAMP_SOURCES:
        raise ValueError(f"stamp_source must be one of {STAMP_SOURCES}, got {stamp_source!r}")
    frame_map = _check_frames(frames)
    role_topics = _role_topics(topics, roles)
    joints_topic = topics.joint_states if joint_states else None
    files, file_warnings = bag_files(spath)
    dec = MessageDecoder(spath, topics, frame_map, stamp_source, image_offset_ns)
    dec.warnings.extend(file_warnings)
    scans = _scan_and_decode(files, dec, topics, set(role_topics.values()), joints_topic)
    dec.path = files[-1] if len(files) == 1 else spath
    rec = _assemble(spath, files, scans, dec, topics, roles, max_pose_gap_ns, base_frame,
                    joints_topic)
    if require:
        _check_complete(rec, scans, topics, role_topics)
    for w in rec.warnings:
        _log.warning("%s: %s", spath, w)
    for r in rec.rectifiers.values():
        # a wide lens loses much of its frame to a pinhole camera without invented border
        (_log.warning if r.kept_fraction < 0.6 else _log.info)("%s: %s", spath, r.describe())
    return rec


def _scan_and_decode(files: list[str], dec: MessageDecoder, topics: TopicMap,
                     image_topics: set[str], joints_topic: str | None) -> list[Scan]:
    """Scan each file (keeping the role topics' messages) and decode it into ``dec``."""
    wanted = {topics.tf, topics.tf_static} | {topics.calibration} | image_topics
    if joints_topic:
        wanted.add(joints_topic)
    scans: list[Scan] = []
    for f in files:
        scan = scan_file(f, wanted.__contains__)
        prefix = f"{os.path.basename(f)}: " if len(files) > 1 else ""
        dec.warnings.extend(prefix + w for w in scan.warnings)
        decode_scan(scan, dec, topics, image_topics, joints_topic)
        scans.append(scan)
    return scans


def _assemble(path: str, files: list[str], scans: list[Scan], dec: MessageDecoder,
              topics: TopicMap, roles: tuple[str, ...], max_gap_ns: int, base_frame: str,
              joints_topic: str | None) -> Recording:
    """The :class:`Recording` of the decoded messages (transforms checked, images sorted)."""
    for topic, n in dec.no_stamp.items():
        dec.warn(f"{topic}: {n} messages have no timestamp (absent, or 0 in a ROS header); "
                 f"used their log time")
    _check_frame_names(dec)
    tf = _build_tf(dec, max_gap_ns)
    metadata: dict[str, dict[str, str]] = {}
    attachments: dict[str, bytes] = {}
    for scan in scans:
        for name, md in scan.metadata.items():
            metadata.setdefault(name, {}).update(md)
        attachments.update(scan.attachments)
    return Recording(path=path, metadata=metadata,
                     calibrations={fid: c[0] for fid, c in dec.calibs.items()}, tf=tf,
                     rectifiers=dict(dec.rectifiers),
                     views=_sorted_images(dec, topics.views) if "views" in roles else [],
                     laser_frames=(_sorted_images(dec, topics.laser) if "laser" in roles
                                   else []),
                     attachments=attachments, warnings=dec.warnings, base_frame=base_frame,
                     topics=_topic_stats(scans, dec),
                     joint_states=_joint_states(dec, joints_topic) if joints_topic else None,
                     frame_names={role: name for role, name in dec.frames.items()
                                  if name != role and name in dec.raw_frames},
                     files=files)


# =========================================================================== assembly
def _build_tf(dec: MessageDecoder, max_gap_ns: int) -> TransformBuffer:
    """The transform tree of the decoded samples, checked (finite, unit quaternions),
    sorted and renormalised, with a warning for each oddity accepted."""
    buf = TransformBuffer(max_gap_ns=max_gap_ns, path=dec.path)
    for (topic, parent, child), link in dec.tf_links.items():
        stamps = np.asarray(link.stamps, dtype=np.int64)
        v = np.asarray(link.values, dtype=np.float64).reshape(-1, 7)
        what = f"transform {parent} -> {child}"
        finite = np.all(np.isfinite(v), axis=1)
        if not np.all(finite):
            i = int(np.argmin(finite))
            raise TransformError(f"{what} is not finite (translation {v[i, :3].tolist()}, "
                                 f"rotation {v[i, 3:].tolist()})", path=dec.path,
                                 topic=topic, time_ns=int(stamps[i]))
        norm = np.linalg.norm(v[:, 3:], axis=1)
        bad = np.abs(norm - 1.0) > QUAT_TOL
        if np.any(bad):
            i = int(np.argmax(bad))
            raise TransformError(f"{what}: rotation {v[i, 3:].tolist()} is not a unit "
                                 f"quaternion (norm {norm[i]:.6g}, tolerance {QUAT_TOL})",
                                 path=dec.path, topic=topic, time_ns=int(stamps[i]))
        v[:, 3:] /= norm[:, None]
        if len(stamps) > 1:
            dif = np.diff(stamps)
            n_back = int(np.sum(dif < 0))
            if n_back:
                dec.warn(f"{topic}: {n_back} timestamps of {what} are out of order "
                          f"(e.g. t={int(stamps[1:][dif < 0][0])} ns after a later one); "
                          f"sorted them")
            order = np.argsort(stamps, kind="stable")
            ss, vs = stamps[order], v[order]
            dup = ss[1:] == ss[:-1]
            if np.any(dup):
                differ = dup & np.any(vs[1:] != vs[:-1], axis=1)
                if np.any(differ):
                    dec.warn(f"{topic}: {int(np.sum(differ))} duplicated timestamps of "
                              f"{what} carry different values (e.g. t="
                              f"{int(ss[1:][differ][0])} ns); kept the last")
        static = topic == dec.topics.tf_static
        if static and len(stamps) > 1 and np.ptp(v, axis=0).max() > 1e-12:
            dec.warn(f"{topic}: static {what} is published {len(stamps)} times with "
                      f"different values; kept the first")
        buf.add(parent, child, stamps, v[:, :3], v[:, 3:], static=static, topic=topic)
    return buf


def _sorted_images(dec: MessageDecoder, topic: str) -> list[ImageMessage]:
    """The images of a topic in time order, the last of exact duplicates kept."""
    msgs = dec.images.get(topic, [])
    if not msgs:
        return []
    stamps = np.array([m.timestamp_ns for m in msgs], dtype=np.int64)
    dif = np.diff(stamps)
    if np.any(dif < 0):
        dec.warn(f"{topic}: {int(np.sum(dif < 0))} image timestamps are out of order; "
                  f"sorted them")
    order = np.argsort(stamps, kind="stable")
    msgs = [msgs[i] for i in order]
    out: list[ImageMessage] = []
    n_dup = 0
    for m in msgs:  # a loop over images (views/frames), not pixels
        if out and out[-1].timestamp_ns == m.timestamp_ns and out[-1].frame_id == m.frame_id:
            out[-1] = m
            n_dup += 1
        else:
            out.append(m)
    if n_dup:
        dec.warn(f"{topic}: {n_dup} images repeat the timestamp and frame_id of another; "
                  f"kept the last of each")
    return out


def _joint_states(dec: MessageDecoder, topic: str) -> JointStates | None:
    """The decoded joint states as one table (None when there are none)."""
    if not dec.joints:
        return None
    names: list[str] = []
    index: dict[str, int] = {}
    for _, ns, _ in dec.joints:  # a loop over messages
        for n in ns:
            if n not in index:
                index[n] = len(names)
                names.append(n)
    order = sorted(range(len(dec.joints)), key=lambda i: dec.joints[i][0])
    pos = np.full((len(dec.joints), len(names)), np.nan)
    for row, i in enumerate(order):
        _, ns, p = dec.joints[i]
        if p:
            pos[row, [index[n] for n in ns]] = p
    stamps = np.array([dec.joints[i][0] for i in order], dtype=np.int64)
    return JointStates(topic=topic, names=names, stamps_ns=stamps, positions=pos)


def _topic_stats(scans: list[Scan], dec: MessageDecoder) -> dict[str, TopicStats]:
    """What every topic holds (read or not), merged over the files; the decoded topics
    with their stamps, in decode order."""
    out: dict[str, TopicStats] = {}
    lt: dict[str, list[int]] = {}
    for scan in scans:
        for cid, ch in scan.channels.items():
            sch = scan.schemas.get(ch.schema_id)
            name = sch.name if sch is not None else ""
            if ch.topic not in out:
                out[ch.topic] = TopicStats(ch.topic, name, ch.message_encoding)
            lt.setdefault(ch.topic, []).extend(scan.log_times.get(cid, []))
        for cid, times in scan.log_times.items():  # messages whose channel was lost
            if cid not in scan.channels:
                key = f"(channel id {cid}, no channel record)"
                out.setdefault(key, TopicStats(key, "", ""))
                lt.setdefault(key, []).extend(times)
    for topic, st in out.items():
        st.log_times_ns = np.asarray(lt.get(topic, []), dtype=np.int64)
        st.count = len(st.log_times_ns)
        t = dec.times.get(topic)
        if t is not None and len(t.stamps) == st.count:
            st.log_times_ns = np.asarray(t.log_times, dtype=np.int64)  # decode order
            st.stamps_ns = np.asarray(t.stamps, dtype=np.int64)
    return out


# =========================================================================== checks
def _check_roles(roles: Iterable[str]) -> tuple[str, ...]:
    """The image roles asked for, as a tuple (one role may be given as a string)."""
    if isinstance(roles, str):
        roles = (roles,)
    out = tuple(roles)
    bad = [r for r in out if r not in _ROLES]
    if bad:
        raise ValueError(f"roles must be among {_ROLES}, got {out!r}")
    return out


def _role_topics(topics: TopicMap, roles: Iterable[str]) -> dict[str, str]:
    """Image role -> its topic."""
    return {r: getattr(topics, r) for r in roles}


def _check_frames(frames: Mapping[str, str] | None) -> dict[str, str]:
    """Validate a role -> recorded-name map; returns it as a plain dict."""
    if frames is None:
        return {}
    out = {str(k): str(v) for k, v in dict(frames).items()}
    bad = [k for k in out if k not in FRAME_ROLES]
    if bad:
        raise ValueError(f"frames keys must be roles among {FRAME_ROLES}, got {sorted(bad)}")
    empty = [k for k, v in out.items() if not v.strip("/")]
    if empty:
        raise ValueError(f"frames must map each role to a non-empty frame name, got "
                         f"{ {k: out[k] for k in empty} }")
    out = {k: (v[1:] if v.startswith("/") else v) for k, v in out.items()}
    names = list(out.values())
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise ValueError(f"frames maps two roles to the same frame name(s) {dup}: {out}")
    return out


def _check_frame_names(dec: MessageDecoder) -> None:
    """A role's recorded name and the role's own name both in the recording: an error."""
    for role, rec in dec.frames.items():
        if rec != role and rec in dec.raw_frames and role in dec.raw_frames:
            raise TransformError(
                f"frames.{role} maps the recorded frame {rec!r} to the role {role!r}, but "
                f"the recording also has a frame named {role!r}: which one is the "
                f"{role} is ambiguous (rename the role's frame in the config to the one "
                f"meant)", path=dec.path)


def _check_complete(rec: Recording, scans: list[Scan], topics: TopicMap,
                    role_topics: dict[str, str]) -> None:
    """``require=True``: every requested role has messages, every image's frame a
    calibration and a transform chain to ``base_frame``; an error names what is missing
    (and what a truncated or damaged file lost)."""
    path = rec.path
    lost = [s.truncated for s in scans if s.truncated]
    trunc = f" (the file is truncated: {'; '.join(lost)})" if lost else ""
    damaged = [d for s in scans for d in s.damaged]
    if damaged:
        trunc += (f" ({len(damaged)} damaged records were skipped: {damaged[0]}"
                  + (", ..." if len(damaged) > 1 else "") + ")")
    present = sorted(t for t, st in rec.topics.items() if st.count)
    for role, topic in role_topics.items():
        n = len(rec.views if role == "views" else rec.laser_frames)
        if n == 0:
            raise RecordingError(f"required topic {topic} has no messages ({role}; topics "
                                 f"with messages: {', '.join(present) or 'none'}; map the "
                                 f"cell's topic names in the config's topics section){trunc}",
                                 path=path, topic=topic)
    images = rec.views + rec.laser_frames
    if not images:
        return
    if not rec.calibrations:
        raise CalibrationError(f"no calibration: topic {topics.calibration} has no messages, "
                               f"but the recording has {len(images)} images{trunc}",
                               path=path, topic=topics.calibration)
    if not rec.tf.links():
        raise TransformError(f"no transforms: topics {topics.tf} and {topics.tf_static} have "
                             f"no messages, but the recording has {len(images)} images{trunc}",
                             path=path, topic=topics.tf)
    checked: set[str] = set()
    for m in images:  # a loop over images, stopping at each new frame_id
        if m.frame_id in checked:
            continue
        rec.camera_for(m)  # CalibrationError naming topic, time and frame_id
        problem = chain_problem(rec.tf, rec.base_frame, m.frame_id)
        if problem:
            hints = []
            if rec.frame_names:
                hints.append("frames renamed from the recording: " + ", ".join(
                    f"{n} -> {r}" for r, n in sorted(rec.frame_names.items())))
            static = rec.topics.get(topics.tf_static)
            if static is None or static.count == 0:
                hints.append(f"topic {topics.tf_static} has no messages: a bag recorded "
                             f"after the static transforms were latched misses them (record "
                             f"{topics.tf_static} with transient_local durability)")
            hint = f" ({'; '.join(hints)})" if hints else ""
            raise TransformError(f"no pose for images of frame_id {m.frame_id!r} in "
                                 f"{rec.base_frame!r}: {problem}{hint}{trunc}", path=path,
                                 topic=m.topic, time_ns=m.timestamp_ns)
        checked.add(m.frame_id)


def chain_problem(tf: TransformBuffer, parent: str, child: str) -> str | None:
    """Why ``child`` cannot be expressed in ``parent`` (structure only), or None.

    Parameters
    ----------
    tf : TransformBuffer
    parent, child : str
        Frame names.

    Returns
    -------
    str or None
        None when a chain of links joins the two frames (whether a pose exists at a given
        time is :meth:`~robo3d.transforms.TransformBuffer.lookup`'s question); else which
        frame is absent, or the two partial chains and the link missing between them.
    """
    parents = {c: p for p, c, _, _ in tf.links()}
    frames = tf.frames
    for f in (parent, child):
        if f not in frames:
            return (f"frame {f!r} is not in the transform tree (frames: "
                    f"{', '.join(sorted(frames)) or 'none'})")

    def up(f: str) -> list[str]:
        chain, seen = [f], {f}
        while chain[-1] in parents and parents[chain[-1]] not in seen:
            chain.append(parents[chain[-1]])
            seen.add(chain[-1])
        return chain

    a, b = up(child), up(parent)
    if set(a) & set(b):
        return None
    return (f"the chain does not connect: {' -> '.join(reversed(a))} and "
            f"{' -> '.join(reversed(b))} have no common frame (missing link between "
            f"{a[-1]!r} and {b[-1]!r})")
