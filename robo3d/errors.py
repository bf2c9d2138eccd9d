"""robo3d's own exception types.

Every error robo3d raises on bad input is a :class:`Robo3dError`, whose message names
the file and, where it applies, the topic, the message time and the frame, so that a
user can find the offending record without a debugger.
"""

from __future__ import annotations

__all__ = [
    "Robo3dError",
    "RecordingError",
    "TransformError",
    "CalibrationError",
    "ImageDecodeError",
    "ConfigError",
    "StageError",
    "NoUsablePoints",
]


class Robo3dError(Exception):
    """Base class of every error robo3d raises on purpose."""


class RecordingError(Robo3dError):
    """A recording that cannot be read, or that breaks the recording contract.

    Parameters
    ----------
    message : str
        What is wrong.
    path : str, optional
        The recording file.
    topic : str, optional
        The topic the offending message came from.
    time_ns : int, optional
        The message's own timestamp (nanoseconds).
    """

    def __init__(
        self,
        message: str,
        *,
        path: str | None = None,
        topic: str | None = None,
        time_ns: int | None = None,
    ) -> None:
        self.path = path
        self.topic = topic
        self.time_ns = time_ns
        self.reason = message
        where = []
        if path is not None:
            where.append(str(path))
        if topic is not None:
            where.append(f"topic {topic}")
        if time_ns is not None:
            where.append(f"t={time_ns} ns ({time_ns / 1e9:.6f} s)")
        prefix = ": ".join([", ".join(where)]) + ": " if where else ""
        super().__init__(prefix + message)


class TransformError(RecordingError):
    """A transform chain that does not connect, or a pose that cannot be interpolated."""


class CalibrationError(RecordingError):
    """Missing, inconsistent or non-finite camera calibration."""


class ImageDecodeError(RecordingError):
    """An image that does not decode, or whose size differs from its calibration."""


class ConfigError(Robo3dError):
    """A configuration key with a wrong name, type or value."""


class StageError(Robo3dError):
    """A pipeline stage that cannot produce its result from its inputs (empty masks,
    no stripe found, degenerate geometry, ...)."""


class NoUsablePoints(StageError):
    """Fusion was given no laser point it can use (none on the object, or none seen from
    its sensor at a usable angle): the fuse stage then closes the surface from the visual
    hull alone, labelled inferred, when there is one."""
