"""The in-memory model of a recording (see ``recording-format.md``).

A :class:`Recording` is what the reader returns and what the writer's users build: the
metadata, the calibrations by ``frame_id``, the transform tree, and the image messages of
each role, kept encoded until a stage decodes them (:meth:`ImageMessage.decode`), so that
a long laser scan costs its compressed size in memory, not its decoded size.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..camera import CameraModel
from ..transforms import TransformBuffer

__all__ = ["ImageMessage", "Recording", "TopicMap"]


@dataclass(frozen=True)
class TopicMap:
    """Which topic carries which role (the config's ``topics`` section)."""

    tf: str = "/tf"
    tf_static: str = "/tf_static"
    calibration: str = "/camera/calibration"
    views: str = "/camera/image"
    laser: str = "/camera/laser_image"
    joint_states: str = "/robot/joint_states"


@dataclass
class ImageMessage:
    """One image as recorded.

    Attributes
    ----------
    topic : str
    timestamp_ns : int
        The message's own ``timestamp`` (not the MCAP log time).
    frame_id : str
    encoding : str
        ``png``, ``jpeg`` (compressed) or ``mono8``, ``rgb8``, ``bgr8``, ``mono16`` (raw).
    data : bytes
        The compressed bytes, or the raw pixel buffer.
    width, height, step : int
        For raw images (0 for compressed ones until decoded).
    path : str
        The recording file, named in decode errors.
    """

    topic: str
    timestamp_ns: int
    frame_id: str
    encoding: str
    data: bytes
    width: int = 0
    height: int = 0
    step: int = 0
    path: str = ""

    def decode(self) -> np.ndarray:
        """The image as ``(H, W)`` or ``(H, W, 3)`` RGB array (uint8 or uint16).

        Raises :class:`~robo3d.errors.ImageDecodeError` naming file, topic and time.
        """
        from .images import decode_image

        return decode_image(self)


@dataclass
class Recording:
    """A whole recording, read into memory with images still encoded."""

    path: str
    metadata: dict[str, dict[str, str]] = field(default_factory=dict)
    calibrations: dict[str, CameraModel] = field(default_factory=dict)
    tf: TransformBuffer = field(default_factory=TransformBuffer)
    views: list[ImageMessage] = field(default_factory=list)
    laser_frames: list[ImageMessage] = field(default_factory=list)
    attachments: dict[str, bytes] = field(default_factory=dict)
    warnings: list[str] = field(default_factory=list)
    base_frame: str = "base"

    @property
    def info(self) -> dict[str, str]:
        """The ``robo3d.recording`` metadata record (empty if absent)."""
        return self.metadata.get("robo3d.recording", {})

    @property
    def workspace(self) -> tuple[np.ndarray, np.ndarray] | None:
        """The workspace box ``(min (3,), max (3,))`` in ``base``, if the recording has one."""
        info = self.info
        if "workspace_min" not in info or "workspace_max" not in info:
            return None
        lo = np.array([float(x) for x in info["workspace_min"].split()])
        hi = np.array([float(x) for x in info["workspace_max"].split()])
        return lo, hi

    def camera_for(self, msg: ImageMessage) -> CameraModel:
        """The calibration matched to an image by ``frame_id`` (error if none)."""
        from ..errors import CalibrationError

        cam = self.calibrations.get(msg.frame_id)
        if cam is None:
            known = ", ".join(sorted(self.calibrations)) or "none"
            raise CalibrationError(
                f"no calibration for frame_id {msg.frame_id!r} (calibrated frames: {known})",
                path=self.path, topic=msg.topic, time_ns=msg.timestamp_ns)
        return cam

    def decode(self, msg: ImageMessage) -> np.ndarray:
        """Decode an image and check its size against its calibration.

        Returns ``(H, W)`` or ``(H, W, 3)`` RGB uint8/uint16 with ``(H, W)`` the size of
        :meth:`camera_for`; raises :class:`~robo3d.errors.CalibrationError` (no
        calibration) or :class:`~robo3d.errors.ImageDecodeError` (bad bytes, wrong size).
        """
        from .images import decode_checked

        return decode_checked(msg, self.camera_for(msg))

    def camera_poses(self, msgs: list[ImageMessage]) -> np.ndarray:
        """``T_base_camera`` ``(N, 4, 4)`` of each image at its own timestamp.

        Images are grouped by ``frame_id``; each group is looked up in one vectorised call.
        """
        out = np.zeros((len(msgs), 4, 4))
        if not msgs:
            return out
        frames = np.array([m.frame_id for m in msgs])
        stamps = np.array([m.timestamp_ns for m in msgs], dtype=np.int64)
        for fid in np.unique(frames):
            sel = np.nonzero(frames == fid)[0]
            try:
                out[sel] = self.tf.lookup(self.base_frame, str(fid), stamps[sel])
            except Exception as exc:  # re-raise with the image topic named
                from ..errors import TransformError

                if isinstance(exc, TransformError):
                    topic = msgs[sel[0]].topic
                    raise TransformError(f"image pose: {exc.reason}", path=self.path,
                                         topic=topic, time_ns=exc.time_ns) from None
                raise
        return out
