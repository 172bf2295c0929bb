"""Settings: each stage's settings dataclass (in its own `stages/<name>/settings.py`) built from
its defaults, a preset, a TOML file and the command line.

Precedence is CLI > config file > preset > dataclass defaults. A config file has one table per
stage (`[prepare]`, `[coarse]`, ...), the run's `[all]`, and optional top-level `device` and `seed`.
"""

from __future__ import annotations

import dataclasses
import types
import typing
from dataclasses import dataclass
from pathlib import Path
from typing import Any

try:
    import tomllib
except ModuleNotFoundError:  # Python 3.10
    import tomli as tomllib  # type: ignore[no-redef]

from .errors import InputError
from .fields import facts, option
from .stages.registry import REGISTRY


@dataclass
class AllConfig:
    """`wgs all` as a whole (the `[all]` table)."""

    budget: str | None = option(
        None,
        "A time budget for the run, such as 10m, 90s or 1h (a bare number is minutes; also [all] budget): the "
        "working size and the training stages' time are chosen to end within it.",
    )


STAGES: dict[str, type] = {s.name: s.settings for s in REGISTRY}  # config table -> settings class
RUN_TABLES: dict[str, type] = {"all": AllConfig}  # config-file tables of a whole run, beside the stages'
# budget presets: each stage's settings under one of these names are its own (`Stage.presets`);
# default is the dataclasses' defaults
PRESET_NAMES = ("fast", "default", "paper")
PRESETS: dict[str, dict[str, dict[str, Any]]] = {
    name: {s.name: s.presets[name] for s in REGISTRY if name in s.presets} for name in PRESET_NAMES
}

GLOBAL_KEYS = {"device": str, "seed": int, "preset": str}


def _accepts(tp: Any, value: Any) -> bool:
    origin = typing.get_origin(tp)
    if origin in (typing.Union, types.UnionType):
        return any(_accepts(a, value) for a in typing.get_args(tp))
    if tp is type(None):
        return value is None
    if tp is float:
        return isinstance(value, int | float) and not isinstance(value, bool)
    if tp is int:
        return isinstance(value, int) and not isinstance(value, bool)
    return isinstance(value, tp)


def field_types(cls: type) -> dict[str, Any]:
    hints = typing.get_type_hints(cls)
    return {f.name: hints[f.name] for f in dataclasses.fields(cls)}


def check_table(cls: type, table: dict[str, Any], where: str, path: str | Path | None = None) -> None:
    """Raise InputError naming the first unknown key or wrongly typed value."""
    types_ = field_types(cls)
    for key, value in table.items():
        if key not in types_:
            raise InputError(f"unknown key '{where}.{key}' (known: {', '.join(sorted(types_))})", path)
        if not _accepts(types_[key], value):
            raise InputError(f"key '{where}.{key}' must be {types_[key]}, got {value!r}", path)


def load_config_file(path: str | Path) -> dict[str, Any]:
    """Read and validate a wgs.toml; returns {'global': {...}, stage: {...}}."""
    path = Path(path)
    try:
        with open(path, "rb") as fh:
            data = tomllib.load(fh)
    except FileNotFoundError:
        raise InputError("config file not found", path) from None
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise InputError(f"not valid TOML: {exc}", path) from None
    out: dict[str, Any] = {"global": {}}
    for key, value in data.items():
        if isinstance(value, dict):
            name = key.replace("-", "_")
            tables = {**STAGES, **RUN_TABLES}
            if name not in tables:
                raise InputError(f"unknown table '[{key}]' (known: {', '.join(tables)})", path)
            check_table(tables[name], value, key, path)
            out[name] = value
        elif key in GLOBAL_KEYS:
            if not isinstance(value, GLOBAL_KEYS[key]) or isinstance(value, bool):
                raise InputError(f"key '{key}' must be {GLOBAL_KEYS[key].__name__}, got {value!r}", path)
            out["global"][key] = value
        else:
            raise InputError(f"unknown key '{key}'", path)
    return out


def resolve(
    stage: str, preset: str | None = None, file_cfg: dict[str, Any] | None = None, cli: dict[str, Any] | None = None
) -> Any:
    """Build a stage's config: defaults < preset < file < CLI (CLI values of None are ignored)."""
    cls = STAGES[stage]
    values: dict[str, Any] = {}
    if preset is not None:
        if preset not in PRESETS:
            raise InputError(f"unknown preset {preset!r} (known: {', '.join(PRESETS)})")
        values.update(PRESETS[preset].get(stage, {}))
    values.update((file_cfg or {}).get(stage, {}))
    values.update({k: v for k, v in (cli or {}).items() if v is not None})
    check_table(cls, values, stage)
    cfg = cls(**values)
    check_choices(cfg)
    return cfg


def as_dict(cfg: Any) -> dict[str, Any]:
    return dataclasses.asdict(cfg)


def _facts_by_field(key: str) -> dict[str, Any]:
    """`key` ("choices" or "range") of every stage config's fields that declare it, by field name
    (one name, one fact, whichever stage's config holds it)."""
    out: dict[str, Any] = {}
    for cls in STAGES.values():
        for f in dataclasses.fields(cls):
            value = facts(cls, f.name).get(key)
            if value is not None:
                if out.setdefault(f.name, value) != value:
                    raise AssertionError(f"field {f.name} declares two {key}")
    return out


# the allowed values of a text field, and the allowed range of a numeric one (inclusive, None:
# open), as the fields declare them (`fields.option`)
CHOICES: dict[str, tuple[str, ...]] = _facts_by_field("choices")
RANGES: dict[str, tuple[float, float | None]] = _facts_by_field("range")


def check_choices(cfg: Any) -> None:
    for key, allowed in CHOICES.items():
        v = getattr(cfg, key, None)
        if v is not None and v not in allowed:
            raise InputError(f"'{key}' must be one of {', '.join(allowed)}, got {v!r}")
    for key, (low, high) in RANGES.items():
        v = getattr(cfg, key, None)
        if v is not None and v < low:
            raise InputError(f"'{key}' must be at least {low}, got {v!r}")
        if v is not None and high is not None and v > high:
            raise InputError(f"'{key}' must be at most {high}, got {v!r}")
