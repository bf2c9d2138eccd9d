"""Reading and writing recordings (``recording-format.md``): Foxglove schemas (protobuf,
JSON) and ROS 2 bags (CDR; a bare ``.mcap`` or a rosbag2 directory).

Modules: ``model`` (the in-memory :class:`Recording`), ``images`` (image codecs),
``framing`` (MCAP records, damaged files), ``decoding`` (messages to values), ``reader``
(assembly and checks: :func:`read_recording`), ``probe`` (:func:`probe_recording`),
``ground_truth`` (:func:`read_ground_truth_tf`), ``writer`` (:class:`RecordingWriter`).
"""

from .images import decode_checked, decode_image, encode_image
from .model import FRAME_ROLES, ImageMessage, JointStates, Recording, TopicMap, TopicStats
from .reader import (
    STAMP_SOURCES,
    RecordingSummary,
    bag_files,
    probe_recording,
    read_ground_truth_tf,
    read_recording,
)
from .writer import RecordingWriter

__all__ = [
    "FRAME_ROLES",
    "STAMP_SOURCES",
    "ImageMessage",
    "JointStates",
    "Recording",
    "TopicMap",
    "TopicStats",
    "RecordingWriter",
    "RecordingSummary",
    "read_recording",
    "probe_recording",
    "bag_files",
    "read_ground_truth_tf",
    "encode_image",
    "decode_image",
    "decode_checked",
]
