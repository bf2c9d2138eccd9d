"""Reading and writing recordings (``recording-format.md``)."""

from .images import decode_checked, decode_image, encode_image
from .model import ImageMessage, Recording, TopicMap
from .reader import RecordingSummary, probe_recording, read_ground_truth_tf, read_recording
from .writer import RecordingWriter

__all__ = [
    "ImageMessage",
    "Recording",
    "TopicMap",
    "RecordingWriter",
    "RecordingSummary",
    "read_recording",
    "probe_recording",
    "read_ground_truth_tf",
    "encode_image",
    "decode_image",
    "decode_checked",
]
