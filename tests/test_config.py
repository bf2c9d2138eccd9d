"""The configuration: config.yaml valid, in step with the schema, bad keys named."""

import pytest
import yaml

from robo3d.config import (
    DEFAULT_CONFIG_PATH,
    default_config,
    load_config,
    load_schema,
    validate_config,
)
from robo3d.errors import ConfigError


def _leaves(schema, prefix=""):
    for key, sub in schema.get("properties", {}).items():
        if sub.get("type") == "object" and "properties" in sub:
            yield from _leaves(sub, prefix + key + ".")
        else:
            yield prefix + key, sub


def test_every_schema_key_has_description_and_default():
    for key, sub in _leaves(load_schema()):
        assert sub.get("description"), f"{key} has no description"
        assert "default" in sub, f"{key} has no default"


def test_config_yaml_lists_every_parameter_at_its_default():
    with open(DEFAULT_CONFIG_PATH) as f:
        shipped = yaml.safe_load(f)
    assert validate_config(shipped) == default_config()
    # and every key is written out in config.yaml, not only implied by the schema
    def keys(d, prefix=""):
        for k, v in d.items():
            if isinstance(v, dict):
                yield from keys(v, prefix + k + ".")
            else:
                yield prefix + k
    assert set(keys(shipped)) == {k for k, _ in _leaves(load_schema())}


def test_unknown_key_is_named():
    with pytest.raises(ConfigError, match=r"carving: .*'resolutoin' was unexpected"):
        validate_config({"carving": {"resolutoin": 64}})


def test_wrong_type_is_named():
    with pytest.raises(ConfigError, match=r"carving\.resolution: 'fine' is not of type"):
        validate_config({"carving": {"resolution": "fine"}})


def test_out_of_bounds_is_named():
    with pytest.raises(ConfigError, match=r"stripes\.band"):
        validate_config({"stripes": {"band": 3.0}})
    with pytest.raises(ConfigError, match=r"segmentation\.polarity"):
        validate_config({"segmentation": {"polarity": "sideways"}})


def test_overrides_merge_and_keep_defaults(tmp_path):
    cfg = load_config(overrides={"carving": {"resolution": 64}, "recordings": "elsewhere"})
    assert cfg["carving"]["resolution"] == 64
    assert cfg["carving"]["outside_image"] == "keep"
    assert cfg["recordings"] == "elsewhere"


def test_unreadable_config_file(tmp_path):
    bad = tmp_path / "c.yaml"
    bad.write_text("carving: [unclosed\n")
    with pytest.raises(ConfigError, match="not valid YAML"):
        load_config(bad)
