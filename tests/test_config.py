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


def test_snakemake_config_strings_are_read_as_the_schema_types():
    """Snakemake reads a nested ``--config`` value with YAML's base loader: every scalar a
    string. Where the schema wants a number, a boolean or null the string is read as one;
    where it admits a string the string stays; a string that is no such value is still
    refused by name."""
    cfg = yaml.safe_load(DEFAULT_CONFIG_PATH.read_text())
    base = yaml.loader.BaseLoader
    cfg["fusion"] = yaml.load("{min_weight: 0.001, fill_holes: false, close: none}",
                              Loader=base)
    cfg["segmentation"] = yaml.load("{threshold: 40, background_topic: null}", Loader=base)
    cfg["evaluation"] = yaml.load("{thresholds_mm: [0.1, 0.2]}", Loader=base)
    cfg["stripes"] = yaml.load("{laser_off_topic: /camera/off, min_peak: 8}", Loader=base)
    assert cfg["fusion"]["min_weight"] == "0.001"  # what Snakemake hands over
    c = validate_config(cfg)
    assert c["fusion"]["min_weight"] == 0.001 and c["fusion"]["fill_holes"] is False
    assert c["fusion"]["close"] == "none"  # an enum of strings: stays a string
    assert c["segmentation"]["threshold"] == 40 and c["segmentation"]["background_topic"] is None
    assert c["evaluation"]["thresholds_mm"] == [0.1, 0.2]
    assert c["stripes"]["laser_off_topic"] == "/camera/off" and c["stripes"]["min_peak"] == 8
    cfg["fusion"] = {"min_weight": "a lot"}
    with pytest.raises(ConfigError, match=r"fusion\.min_weight: 'a lot' is not of type"):
        validate_config(cfg)
