"""Configuration: ``config/config.yaml`` validated against ``config/schema.yaml``.

The schema is the single list of parameters: every key has a description, a default and
bounds. :func:`validate_config` fills defaults and turns the first violation into a
:class:`~robo3d.errors.ConfigError` that names the key, what was expected and what came,
so that a typo fails before any job runs.
"""

from __future__ import annotations

import copy
from pathlib import Path
from typing import Any

import yaml

from .errors import ConfigError

__all__ = ["SCHEMA_PATH", "DEFAULT_CONFIG_PATH", "load_schema", "validate_config", "load_config",
           "default_config"]

_ROOT = Path(__file__).resolve().parents[1]
SCHEMA_PATH = _ROOT / "config" / "schema.yaml"
DEFAULT_CONFIG_PATH = _ROOT / "config" / "config.yaml"


def load_schema(path: str | Path = SCHEMA_PATH) -> dict[str, Any]:
    """The JSON schema (YAML) of the configuration."""
    with open(path, encoding="utf-8") as f:
        return yaml.safe_load(f)


def _fill_defaults(cfg: dict[str, Any], schema: dict[str, Any]) -> None:
    for key, sub in schema.get("properties", {}).items():
        if key not in cfg and "default" in sub:
            cfg[key] = copy.deepcopy(sub["default"])
        if isinstance(cfg.get(key), dict) and sub.get("type") == "object":
            _fill_defaults(cfg[key], sub)


def _schema_types(schema: dict[str, Any]) -> set[str]:
    """The JSON types a (sub)schema admits, its ``oneOf``/``anyOf`` alternatives included."""
    t = schema.get("type")
    out = {t} if isinstance(t, str) else set(t or ())
    for alt in (*schema.get("oneOf", ()), *schema.get("anyOf", ())):
        out |= _schema_types(alt)
    return out


def _is_type(value: Any, t: str) -> bool:
    return {"number": isinstance(value, (int, float)) and not isinstance(value, bool),
            "integer": isinstance(value, int) and not isinstance(value, bool),
            "boolean": isinstance(value, bool), "null": value is None,
            "array": isinstance(value, list), "object": isinstance(value, dict)}.get(t, False)


def _coerce_strings(value: Any, schema: dict[str, Any]) -> Any:
    """``value`` with the strings that stand for a number, a boolean or null read as such
    where the schema admits that type (in place for mappings).

    Why: Snakemake reads a nested ``--config`` value (``--config 'fusion={min_weight:
    0.001}'``) with YAML's base loader, which leaves every scalar a string; the schema
    then refused ``'0.001'`` as not a number. A string stays a string where the schema
    admits strings, except YAML's null (``null``, ``~``) where it admits null too."""
    if isinstance(value, dict):
        props = schema.get("properties", {})
        extra = schema.get("additionalProperties")
        for k, v in value.items():
            sub = props.get(k, extra if isinstance(extra, dict) else None)
            if sub is not None:
                value[k] = _coerce_strings(v, sub)
        return value
    if isinstance(value, list) and isinstance(schema.get("items"), dict):
        return [_coerce_strings(v, schema["items"]) for v in value]
    if not isinstance(value, str):
        return value
    types = _schema_types(schema)
    if "null" in types and value in ("null", "~", "Null", "NULL"):
        return None
    if not types or "string" in types:
        return value
    try:
        parsed = yaml.safe_load(value)
    except yaml.YAMLError:
        return value
    if any(_is_type(parsed, t) for t in types):
        return _coerce_strings(parsed, schema) if isinstance(parsed, (list, dict)) else parsed
    return value


def validate_config(config: dict[str, Any], schema: dict[str, Any] | None = None) -> dict[str, Any]:
    """Validate a configuration and fill in defaults.

    Parameters
    ----------
    config : dict
        The configuration as loaded (Snakemake's ``config`` or a parsed YAML file).
    schema : dict, optional
        The schema; ``config/schema.yaml`` by default.

    Returns
    -------
    dict
        A new dict with every default filled in.

    Raises
    ------
    ConfigError
        Naming the offending key (``carving.resolution``), the value and the rule.
    """
    import jsonschema

    schema = load_schema() if schema is None else schema
    if not isinstance(config, dict):
        raise ConfigError(f"configuration must be a mapping, got {type(config).__name__}")
    cfg = _coerce_strings(copy.deepcopy(config), schema)
    _fill_defaults(cfg, schema)
    validator = jsonschema.Draft202012Validator(schema)
    errors = sorted(validator.iter_errors(cfg), key=lambda e: list(e.absolute_path))
    if errors:
        e = errors[0]
        key = ".".join(str(p) for p in e.absolute_path) or "(top level)"
        if e.validator == "additionalProperties":
            allowed = sorted(e.schema.get("properties", {}))
            msg = f"config key {key}: {e.message}; allowed keys: {', '.join(allowed)}"
        else:
            desc = e.schema.get("description")
            msg = f"config key {key}: {e.message}" + (f" ({desc})" if desc else "")
        more = f" (and {len(errors) - 1} more problem(s))" if len(errors) > 1 else ""
        raise ConfigError(msg + more)
    return cfg


def load_config(path: str | Path | None = None,
                overrides: dict[str, Any] | None = None) -> dict[str, Any]:
    """Read a YAML configuration (``config/config.yaml`` by default), apply overrides
    (top-level keys, or nested dicts merged one level deep), validate and fill defaults."""
    path = DEFAULT_CONFIG_PATH if path is None else Path(path)
    try:
        with open(path, encoding="utf-8") as f:
            cfg = yaml.safe_load(f) or {}
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read the configuration: {exc}") from None
    except yaml.YAMLError as exc:
        raise ConfigError(f"{path}: not valid YAML: {exc}") from None
    for k, v in (overrides or {}).items():
        if isinstance(v, dict) and isinstance(cfg.get(k), dict):
            cfg[k] = {**cfg[k], **v}
        else:
            cfg[k] = v
    return validate_config(cfg)


def default_config() -> dict[str, Any]:
    """Every parameter at its schema default."""
    return validate_config({})
