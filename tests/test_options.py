"""Every algorithm's options dataclass against the schema: the same keys, the same
defaults (robo3d.options)."""

import dataclasses
import importlib
import pkgutil

import pytest

import robo3d
from robo3d.config import default_config
from robo3d.errors import ConfigError
from robo3d.options import Options, option_classes


def _all_option_classes():
    for m in pkgutil.walk_packages(robo3d.__path__, "robo3d."):
        if not m.name.startswith("robo3d.sim"):
            importlib.import_module(m.name)
    return [c for c in option_classes() if c.__module__.startswith("robo3d.")]


def test_option_defaults_are_the_schema_defaults():
    cfg = default_config()
    classes = _all_option_classes()
    for cls in classes:
        assert cls.section in cfg, f"{cls.__name__}.section {cls.section!r} is no config section"
        section = cfg[cls.section]
        for f in dataclasses.fields(cls):
            if f.name in cls.not_in_config:
                continue
            assert f.name in section, f"{cls.__name__}.{f.name}: no key {cls.section}.{f.name}"
            default = (f.default_factory() if f.default_factory is not dataclasses.MISSING
                       else f.default)
            assert default == section[f.name], (
                f"{cls.__name__}.{f.name} defaults to {default!r}, the schema to "
                f"{section[f.name]!r}")
        # made from the default config, the options are the class's defaults
        extra = {n: getattr(cls(), n) for n in cls.not_in_config}
        assert cls.from_config(section, **extra) == cls()


def test_missing_key_is_named():
    @dataclasses.dataclass(frozen=True)
    class _Demo(Options):
        section = "demo"
        size_m: float = 1.0

    with pytest.raises(ConfigError, match="demo.size_m"):
        _Demo.from_config({})
    assert _Demo.from_config({"size_m": 2.0, "other": 1}).size_m == 2.0
    with pytest.raises(TypeError, match="nope"):
        _Demo.from_config({"size_m": 2.0}, nope=1)
