"""Click options derived from the config dataclasses.

Everything about an option comes from its field (`wgs.fields.option`): its type, its help (what
the field means), its choices or range, and the "(default X)" its help states; a stage's own
command and `wgs all` share it. Every option's click default is None: the config resolves
defaults < preset < file < CLI.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import click

from ..config import PRESETS, STAGES, field_types
from ..fields import facts, option
from ..stages.registry import REGISTRY


def _shown(value: Any) -> str:
    return "none" if value is None else str(value).lower() if isinstance(value, bool) else str(value)


def click_type(facts_: Mapping[str, Any], tp: Any) -> click.ParamType:
    """The click type of a field with these facts: its choices, its range, or its plain type."""
    if facts_.get("choices") is not None:
        return click.Choice(facts_["choices"])
    if facts_.get("range") is not None:
        low, high = facts_["range"]
        if tp is int:
            return click.IntRange(min=int(low), max=None if high is None else int(high))
        return click.FloatRange(min=low, max=high)
    plain: dict[Any, click.ParamType] = {int: click.INT, float: click.FLOAT, Path: click.Path(path_type=Path)}
    return plain.get(tp, click.STRING)


def field_option(cls: type, name: str, from_config: bool) -> Callable:
    """The click option of field `name` of dataclass `cls`, from its facts (`fields.option`): its
    names (--name-with-dashes unless `flags`), type, choices or range, metavar and help.
    from_config: a stage config's field, whose value the config resolves (defaults < preset < file
    < command line): click's default is None and the help states the config's default, and a bool
    is --name/--no-name; else a command's own setting, whose click default is the field's (click
    states it) and a bool a flag."""
    meta = facts(cls, name)
    tp = field_types(cls)[name]
    base = next((a for a in getattr(tp, "__args__", (tp,)) if a is not type(None)), tp)
    default = next(f.default for f in dataclasses.fields(cls) if f.name == name)
    flag = "--" + name.replace("_", "-")
    text = meta["help"]
    if from_config and default is not None:
        text = f"{text} (default {_shown(default)})"
    if base is bool:  # --name/--no-name (None: the config decides) or a plain flag
        if from_config:
            return click.option(*meta.get("flags", (f"{flag}/--no-{flag[2:]}",)), name, default=None, help=text)
        return click.option(*meta.get("flags", (flag,)), name, is_flag=True, default=default, help=text)
    return click.option(
        *meta.get("flags", (flag,)),
        name,
        type=click_type(meta, base),
        default=None if from_config else default,
        required=meta.get("required", False),
        metavar=meta.get("metavar"),
        help=text,
    )


def settings_options(cls: type) -> Callable:
    """A command's options from its settings dataclass, one per field in order (`field_option`)."""

    def apply(f: Callable) -> Callable:
        for field in reversed(dataclasses.fields(cls)):
            f = field_option(cls, field.name, from_config=False)(f)
        return f

    return apply


@dataclasses.dataclass
class ModelChoice:
    """Which trained model a command reads."""

    stage: str | None = option(
        None, "Which model (default: the newest, fine when it exists).", choices=("coarse", "fine")
    )


def config_option(table: str, name: str) -> Callable:
    """The click option of field `name` of stage table `table`'s config (`field_option`)."""
    return field_option(STAGES[table], name, from_config=True)


def config_options(table: str, *names: str) -> Callable:
    """`config_option` for several fields of one table, listed in the help in the given order."""

    def apply(f: Callable) -> Callable:
        for name in reversed(names):
            f = config_option(table, name)(f)
        return f

    return apply


@dataclasses.dataclass
class PresetChoice:
    preset: str | None = option(None, "Budget preset.", choices=tuple(PRESETS))


preset_option = settings_options(PresetChoice)


def all_fields() -> dict[str, tuple[str, ...]]:
    """`wgs all`'s options from the stages' settings (`Stage.all_options`): field -> the stages it
    sets, in the registry's order."""
    out: dict[str, tuple[str, ...]] = {}
    for stage in REGISTRY:
        for name in stage.all_options:
            out[name] = out.get(name, ()) + (stage.name,)
    return out


ALL_FIELDS = all_fields()


def all_options(f):
    for name, tables in reversed(ALL_FIELDS.items()):
        f = config_option(tables[0], name)(f)
    return f


def all_overrides(options: dict) -> dict[str, dict]:
    """`wgs all`'s option values as per-table overrides of the stages' configs."""
    out: dict[str, dict] = {}
    for name, tables in ALL_FIELDS.items():
        for table in tables:
            out.setdefault(table, {})[name] = options[name]
    return out
