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

from ..config import CHOICES, PRESETS, RANGES, STAGES, field_types
from ..fields import facts, option

# flags whose names differ from their field: field -> click declaration
FLAG_NAMES: dict[str, str] = {"use_u": "--u/--no-u"}
# what a value looks like where its type says too little
METAVARS: dict[str, str] = {
    "prior": "builtin|none|DIR",
    "masks": "auto|none|DIR",
    "sd_model": "DIR",
    "controlnet": "DIR",
    "lpips_weights": "DIR",
}


def _shown(value: Any) -> str:
    return "none" if value is None else str(value).lower() if isinstance(value, bool) else str(value)


def option_type(name: str, tp: Any) -> click.ParamType:
    """The click type of a config field: its choices, its range, or its plain type."""
    return click_type({"choices": CHOICES.get(name), "range": RANGES.get(name)}, tp)


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


def settings_options(cls: type) -> Callable:
    """A command's options from its settings dataclass (`fields.option`), one per field in order:
    typed, with the field's meaning as help, its choices or range, and its default (which click
    states, `show_default`). A bool field is a flag."""
    types = field_types(cls)

    def one(field: dataclasses.Field) -> Callable:
        meta = facts(cls, field.name)
        tp = types[field.name]
        base = next((a for a in getattr(tp, "__args__", (tp,)) if a is not type(None)), tp)
        decls = meta.get("flags", ("--" + field.name.replace("_", "-"),))
        text = meta["help"]
        if base is bool:
            return click.option(*decls, field.name, is_flag=True, default=field.default, help=text)
        return click.option(
            *decls,
            field.name,
            type=click_type(meta, base),
            default=field.default,
            required=meta.get("required", False),
            help=text,
        )

    def apply(f: Callable) -> Callable:
        for field in reversed(dataclasses.fields(cls)):
            f = one(field)(f)
        return f

    return apply


@dataclasses.dataclass
class ModelChoice:
    """Which trained model a command reads."""

    stage: str | None = option(
        None, "Which model (default: the newest, fine when it exists).", choices=("coarse", "fine")
    )


def config_option(table: str, name: str) -> Callable:
    """A click option for field `name` of stage table `table`'s config: `--name-with-dashes`
    (or `FLAG_NAMES`), typed, validated and with its default stated from the config."""
    cls = STAGES[table]
    tp = field_types(cls)[name]
    base = next((a for a in getattr(tp, "__args__", (tp,)) if a is not type(None)), tp)
    default = next(f.default for f in dataclasses.fields(cls) if f.name == name)
    text = facts(cls, name)["help"]
    if default is not None:
        text = f"{text} (default {_shown(default)})"
    flag = "--" + name.replace("_", "-")
    if base is bool:
        decl = FLAG_NAMES.get(name, f"{flag}/--no-{flag[2:]}")
        return click.option(decl, name, default=None, help=text)
    return click.option(
        FLAG_NAMES.get(name, flag),
        name,
        type=option_type(name, base),
        default=None,
        help=text,
        metavar=METAVARS.get(name),
    )


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


# `wgs all`'s own options: config field -> the stage tables it sets
ALL_FIELDS: dict[str, tuple[str, ...]] = {
    "views": ("prepare",),
    "downscale": ("prepare",),
    "max_size": ("prepare",),
    "matcher": ("prepare",),
    "masks": ("prepare",),
    "mirror": ("prepare",),
    "ensemble": ("coarse",),
    "strategy": ("mask_data",),
    "domain": ("finetune",),
    "use_u": ("finetune",),
    "prior": ("finetune",),
    "carve": ("repair",),
    "shape_revolution": ("repair",),
    "shape_smooth": ("repair",),
    "lpips_weights": ("fine", "eval"),
}


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
