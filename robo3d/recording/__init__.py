"""Reading and writing recordings (``recording-format.md``)."""

from .model import ImageMessage, Recording, TopicMap

__all__ = ["ImageMessage", "Recording", "TopicMap"]
