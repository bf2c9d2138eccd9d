"""The in-memory model of a recording (see ``recording-format.md``).

A :class:`Recording` is what the reader returns and what the writer's users build: the
metadata, the calibrations by ``frame_id``, the transform tree, and the image messages of
each role, kept encoded until a stage decodes them (:meth:`ImageMessage.decode`), so that
a long laser scan costs its compressed size in memory, not its decoded size.

Frame names in a :class:`Recording` are the *roles* of ``recording-format.md``
(``base``, ``flange``, ``camera``, ``laser``) wherever the reader was told which
recorded name plays which role (``frames=``, the config's ``frames`` section): a ROS 2
cell's ``base_link`` is ``base`` here, and :attr:`Recording.frame_names` keeps the
recorded names.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..camera import CameraModel, Rectifier
from ..errors import CalibrationError, RecordingError, TransformError
from ..transforms import TransformBuffer
from .images import decode_checked, decode_image

__all__ = ["ImageMessage", "Recording", "TopicMap", "TopicStats", "JointStates", "FRAME_ROLES",
           "DEFAULT_TOPICS"]

#: The frame roles of ``recording-format.md``.
FRAME_ROLES: tuple[str, ...] = ("base", "flange", "camera", "laser")


@dataclass(frozen=True)
class TopicMap:
    """Which topic carries which role (the config's ``topics`` section)."""

    tf: str = "/tf"
    tf_static: str = "/tf_static"
    calibration: str = "/camera/calibration"
    views: str = "/camera/image"
    laser: str = "/camera/laser_image"
    joint_states: str = "/robot/joint_states"


#: The contract's default topic names (``recording-format.md``, Topics).
DEFAULT_TOPICS = TopicMap()


@dataclass
class TopicStats:
    """What a recording holds on one topic (every topic, read or not).

    Attributes
    ----------
    topic, schema, encoding : str
        Topic name, schema name and message encoding (``protobuf``, ``json``, ``cdr``).
    count : int
        Messages found intact.
    log_times_ns : (count,) int64
        MCAP log times in file order (nanoseconds).
    stamps_ns : (count,) int64 or None
        The messages' own stamps, for the topics the reader decoded (a tf message: its
        first transform's stamp); None for topics it skipped.
    """

    topic: str
    schema: str
    encoding: str
    count: int = 0
    log_times_ns: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    stamps_ns: np.ndarray | None = None


@dataclass
class JointStates:
    """Joint positions as recorded (``sensor_msgs/msg/JointState``): informational only.

    Attributes
    ----------
    topic : str
    names : list of str
        Every joint named by any message, in order of first appearance.
    stamps_ns : (N,) int64
        One per message, sorted.
    positions : (N, J) float64
        Radians or metres; NaN where a message lacks the joint.
    """

    topic: str
    names: list[str]
    stamps_ns: np.ndarray
    positions: np.ndarray


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
        ``png``, ``jpeg`` (compressed) or a raw encoding (``images.READ_RAW_ENCODINGS``:
        ``mono8``, ``rgb8``, ``bgr8``, ``mono16``, Bayer, YUV 4:2:2, ...).
    data : bytes
        The compressed bytes, or the raw pixel buffer.
    width, height, step : int
        For raw images (0 for compressed ones until decoded).
    path : str
        The recording file, named in decode errors.
    log_time_ns : int
        The MCAP log time (when the recorder received it).
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
    log_time_ns: int = 0

    def decode(self) -> np.ndarray:
        """The image as ``(H, W)`` or ``(H, W, 3)`` RGB array (uint8 or uint16).

        Raises :class:`~robo3d.errors.ImageDecodeError` naming file, topic and time.
        """
        return decode_image(self)


@dataclass
class Recording:
    """A whole recording, read into memory with images still encoded.

    ``topics`` describes every topic found (counts, log times); ``frame_names`` maps each
    role to the recorded frame name it was read from (only roles that were renamed);
    ``files`` lists the MCAP files read (several for a split rosbag2 directory).
    """

    path: str
    metadata: dict[str, dict[str, str]] = field(default_factory=dict)
    calibrations: dict[str, CameraModel] = field(default_factory=dict)
    rectifiers: dict[str, Rectifier] = field(default_factory=dict)
    tf: TransformBuffer = field(default_factory=TransformBuffer)
    views: list[ImageMessage] = field(default_factory=list)
    laser_frames: list[ImageMessage] = field(default_factory=list)
    attachments: dict[str, bytes] = field(default_factory=dict)
    warnings: list[str] = field(default_factory=list)
    base_frame: str = "base"
    topics: dict[str, TopicStats] = field(default_factory=dict)
    joint_states: JointStates | None = None
    frame_names: dict[str, str] = field(default_factory=dict)
    files: list[str] = field(default_factory=list)

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
        try:
            lo = np.array([float(x) for x in info["workspace_min"].split()])
            hi = np.array([float(x) for x in info["workspace_max"].split()])
        except ValueError as exc:
            raise RecordingError(f"metadata robo3d.recording: workspace_min/workspace_max must "
                                 f"be 'x y z' numbers, got {info['workspace_min']!r} and "
                                 f"{info['workspace_max']!r} ({exc})", path=self.path) from None
        if lo.shape != (3,) or hi.shape != (3,) or not (np.all(np.isfinite(lo))
                                                        and np.all(np.isfinite(hi))):
            raise RecordingError(f"metadata robo3d.recording: workspace_min/workspace_max must "
                                 f"be three finite numbers each, got {info['workspace_min']!r} "
                                 f"and {info['workspace_max']!r}", path=self.path)
        return lo, hi

    def camera_for(self, msg: ImageMessage) -> CameraModel:
        """The calibration matched to an image by ``frame_id`` (error if none)."""
        cam = self.calibrations.get(msg.frame_id)
        if cam is None:
            known = ", ".join(sorted(self.calibrations)) or "none"
            raise CalibrationError(
                f"no calibration for frame_id {msg.frame_id!r} (calibrated frames: {known})",
                path=self.path, topic=msg.topic, time_ns=msg.timestamp_ns)
        return cam

    def decode(self, msg: ImageMessage) -> np.ndarray:
        """Decode an image and check its size against its calibration; the image of a
        ``rational_polynomial`` camera (:attr:`rectifiers`) resampled to the pinhole
        camera that :meth:`camera_for` gives.

        Returns ``(H, W)`` or ``(H, W, 3)`` RGB uint8/uint16 with ``(H, W)`` the size of
        :meth:`camera_for`; raises :class:`~robo3d.errors.CalibrationError` (no
        calibration) or :class:`~robo3d.errors.ImageDecodeError` (bad bytes, wrong size).
        """
        img = self.decode_raw(msg)
        rect = self.rectifiers.get(msg.frame_id)
        return img if rect is None else rect(img)

    def decode_raw(self, msg: ImageMessage) -> np.ndarray:
        """:meth:`decode` without the rectification: the image as recorded (the calibrate
        stage estimates its own lens model from the raw images)."""
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
                if isinstance(exc, TransformError):
                    topic = msgs[sel[0]].topic
                    raise TransformError(f"image pose: {exc.reason}", path=self.path,
                                         topic=topic, time_ns=exc.time_ns) from None
                raise
        return out
