"""Typed options of the algorithms, made from their config sections without renaming.

Each algorithm that a stage runs takes its parameters as one frozen dataclass, a subclass
of :class:`Options` (``SegmentOptions``, ``AlignOptions``, ...). Its field names are the
config keys of its section in ``config/schema.yaml`` (units and all: ``voxel_size_m``,
``max_fill_distance_mm``), so a stage builds it with one call and renames nothing::

    opts = AlignOptions.from_config(cfg["alignment"])
    result = align_sweeps(points, normals, options=opts, ...)

The section's other keys belong to the stage (``enabled``, output switches, ...). The
defaults of the fields are the schema's; ``tests/test_options.py`` checks every subclass
against the schema, so a default cannot drift from the documented one.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from typing import Any, ClassVar, TypeVar

from .errors import ConfigError

__all__ = ["Options", "option_classes"]

T = TypeVar("T", bound="Options")


@dataclasses.dataclass(frozen=True)
class Options:
    """Base of the algorithms' option dataclasses.

    Subclasses set ``section`` (the config section the fields come from, e.g.
    ``"alignment"``) and declare one field per config key they use. A field may also be
    a parameter that is not in the config (it keeps its dataclass default then); list
    such fields in ``not_in_config``.
    """

    section: ClassVar[str] = ""
    not_in_config: ClassVar[tuple[str, ...]] = ()

    @classmethod
    def from_config(cls: type[T], section: Mapping[str, Any], **extra: Any) -> T:
        """The options from a validated config section (``cfg[cls.section]``).

        ``extra`` sets fields that are not config keys (``not_in_config``), e.g. the
        recording's seed. A config key the class needs and the section lacks is a
        :class:`~robo3d.errors.ConfigError` naming it.
        """
        values: dict[str, Any] = {}
        for f in dataclasses.fields(cls):
            if f.name in extra:
                values[f.name] = extra[f.name]
            elif f.name in cls.not_in_config:
                continue
            elif f.name in section:
                values[f.name] = section[f.name]
            else:
                raise ConfigError(f"config key {cls.section}.{f.name} is missing "
                                  f"({cls.__name__} needs it)")
        unknown = set(extra) - {f.name for f in dataclasses.fields(cls)}
        if unknown:
            raise TypeError(f"{cls.__name__} has no option(s) {sorted(unknown)}")
        return cls(**values)

    def replace(self: T, **changes: Any) -> T:
        """A copy with some options changed."""
        return dataclasses.replace(self, **changes)

    def as_dict(self) -> dict[str, Any]:
        """The options as a plain dict (for reports)."""
        return dataclasses.asdict(self)


def option_classes() -> list[type[Options]]:
    """Every :class:`Options` subclass defined by the modules imported so far."""
    out, todo = [], list(Options.__subclasses__())
    while todo:
        c = todo.pop()
        out.append(c)
        todo.extend(c.__subclasses__())
    return sorted(out, key=lambda c: (c.__module__, c.__name__))
