"""A recording's true transforms (attachment ``ground_truth/tf.json``), for evaluation.

``recording-format.md`` (Metadata and attachments) gives the truth as a
``foxglove.FrameTransforms`` message in JSON, the same form as ``/tf`` in a JSON
recording (https://docs.foxglove.dev/docs/visualization/message-schemas/frame-transforms);
robo3d's simulator first wrote another form, which is read too
(:func:`read_ground_truth_tf`). The pipeline never reads it except to evaluate.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from typing import Any

import numpy as np

from ..errors import RecordingError
from ..transforms import TransformBuffer
from .decoding import QUAT_TOL
from .model import Recording

__all__ = ["GROUND_TRUTH_TF", "read_ground_truth_tf"]

#: Name of the attachment holding the true ``base -> flange`` samples.
GROUND_TRUTH_TF = "ground_truth/tf.json"


def read_ground_truth_tf(recording: Recording) -> TransformBuffer:
    """The true transforms of a recording (attachment ``ground_truth/tf.json``).

    Two forms are read:

    - the contract's (``recording-format.md``): a ``foxglove.FrameTransforms`` message in
      JSON, ``{"transforms": [{"timestamp": {"sec", "nsec"}, "parent_frame_id",
      "child_frame_id", "translation": {"x", "y", "z"}, "rotation": {"x", "y", "z",
      "w"}}, ...]}``, one entry per sample (the protobuf-style ``{"seconds", "nanos"}``
      timestamp is accepted too). The truth names only the links that carry error; every
      static link of the recording (``/tf_static``) that the truth does not name is
      taken as true and added;
    - robo3d's first form (the demo recordings): ``{"transforms": [{"parent", "child",
      "stamps_ns": [N], "translations": [[x, y, z]] * N, "quaternions": [[x, y, z, w]] *
      N}, ...]}`` (an optional ``"static": true`` marks a fixed link).

    Metres, nanoseconds. Evaluation only: the pipeline must never use it to measure.

    Parameters
    ----------
    recording : Recording

    Returns
    -------
    TransformBuffer
        With the same ``max_gap_ns`` as ``recording.tf``.

    Raises
    ------
    RecordingError
        The attachment is absent or malformed (non-finite, non-unit quaternions, ragged
        arrays).
    """
    path = recording.path
    data = recording.attachments.get(GROUND_TRUTH_TF)
    if data is None:
        raise RecordingError(f"no {GROUND_TRUTH_TF} attachment (attachments: "
                             f"{', '.join(sorted(recording.attachments)) or 'none'})", path=path)

    def fail(what: str) -> RecordingError:
        return RecordingError(f"attachment {GROUND_TRUTH_TF}: {what}", path=path)

    try:
        doc = json.loads(data)
    except (ValueError, UnicodeDecodeError) as exc:
        raise fail(f"is not valid JSON ({exc})") from None
    entries = doc.get("transforms") if isinstance(doc, dict) else None
    if not isinstance(entries, list):
        raise fail('must be {"transforms": [...]}')
    buf = TransformBuffer(max_gap_ns=recording.tf.max_gap_ns, path=path)
    if entries and isinstance(entries[0], dict) and "child_frame_id" in entries[0]:
        from ..transforms import matrix_to_quat

        _ground_truth_frame_transforms(entries, buf, fail)
        named = {child for _, child, _, _ in buf.links()}
        for parent, child, static, _ in recording.tf.links():
            if static and child not in named:
                st, t = recording.tf.link_samples(parent, child)
                buf.add(parent, child, st, t[:, :3, 3], matrix_to_quat(t[:, :3, :3]),
                        static=True, topic="/tf_static")
        return buf
    for i, e in enumerate(entries):
        try:
            parent, child = str(e["parent"]), str(e["child"])
            stamps = np.asarray(e["stamps_ns"], dtype=np.int64).reshape(-1)
            tr = np.asarray(e["translations"], dtype=np.float64)
            q = np.asarray(e["quaternions"], dtype=np.float64)
            static = bool(e.get("static", False))
        except (KeyError, TypeError, ValueError, OverflowError) as exc:
            raise fail(f"transforms[{i}] needs parent, child, stamps_ns, translations, "
                       f"quaternions ({type(exc).__name__}: {exc})") from None
        n = len(stamps)
        if n == 0 or tr.shape != (n, 3) or q.shape != (n, 4):
            raise fail(f"transforms[{i}] ({parent} -> {child}): expected {n} stamps, (N, 3) "
                       f"translations and (N, 4) quaternions, got {tr.shape} and {q.shape}")
        if not (np.all(np.isfinite(tr)) and np.all(np.isfinite(q))):
            raise fail(f"transforms[{i}] ({parent} -> {child}) has non-finite values")
        norm = np.linalg.norm(q, axis=1)
        if np.any(np.abs(norm - 1) > QUAT_TOL):
            raise fail(f"transforms[{i}] ({parent} -> {child}) has non-unit quaternions "
                       f"(norms {norm.min():.6g} .. {norm.max():.6g})")
        buf.add(parent, child, stamps, tr, q, static=static, topic=GROUND_TRUTH_TF)
    return buf


def _ground_truth_frame_transforms(entries: list[Any], buf: TransformBuffer,
                                   fail: Callable[[str], RecordingError]) -> None:
    """Add the samples of a ``foxglove.FrameTransforms`` JSON truth to ``buf``, per link."""
    links: dict[tuple[str, str], tuple[list[int], list[list[float]], list[list[float]]]] = {}
    for i, e in enumerate(entries):
        try:
            parent, child = str(e["parent_frame_id"]), str(e["child_frame_id"])
            ts = e["timestamp"]
            if "sec" in ts:
                stamp = int(ts["sec"]) * 1_000_000_000 + int(ts.get("nsec", 0))
            else:
                stamp = int(ts["seconds"]) * 1_000_000_000 + int(ts.get("nanos", 0))
            tr = [float(e["translation"][k]) for k in "xyz"]
            q = [float(e["rotation"][k]) for k in "xyzw"]
        except (KeyError, TypeError, ValueError, OverflowError, AttributeError) as exc:
            raise fail(f"transforms[{i}] needs timestamp {{sec, nsec}}, parent_frame_id, "
                       f"child_frame_id, translation {{x, y, z}}, rotation {{x, y, z, w}} "
                       f"({type(exc).__name__}: {exc})") from None
        if not (np.all(np.isfinite(tr)) and np.all(np.isfinite(q))):
            raise fail(f"transforms[{i}] ({parent} -> {child}) has non-finite values")
        if abs(float(np.linalg.norm(q)) - 1) > QUAT_TOL:
            raise fail(f"transforms[{i}] ({parent} -> {child}) has a non-unit quaternion "
                       f"(norm {np.linalg.norm(q):.6g})")
        if stamp < 0:
            raise fail(f"transforms[{i}] ({parent} -> {child}) has a negative timestamp")
        s_, t_, q_ = links.setdefault((parent, child), ([], [], []))
        s_.append(stamp)
        t_.append(tr)
        q_.append(q)
    for (parent, child), (st, tr, q) in links.items():
        buf.add(parent, child, np.array(st, dtype=np.int64), np.array(tr), np.array(q),
                topic=GROUND_TRUTH_TF)
