"""What a settings field says of itself: what it means on the command line, its choices or its
range. The config dataclasses (`wgs.config` and the library's parameter dataclasses it extends)
declare their options with `option`; the command line (`wgs.cli.options`) and the config-file
check (`config.check_choices`) read them back with `facts`."""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from typing import Any


def option(
    default: Any,
    meaning: str | None = None,
    *,
    choices: tuple[str, ...] | None = None,
    bounds: tuple[float, float | None] | None = None,
    flags: tuple[str, ...] | None = None,
    metavar: str | None = None,
    required: bool = False,
) -> Any:
    """A dataclass field with its default and its facts: `meaning` (the command line's help; None:
    not offered there), `choices`, `bounds` (inclusive; None: open), `flags` (its names on the
    command line where they are not --field-name), `metavar` (what a value looks like where its type
    says too little), `required` (a command's option without default)."""
    meta: dict[str, Any] = {}
    if flags is not None:
        meta["flags"] = flags
    if metavar is not None:
        meta["metavar"] = metavar
    if required:
        meta["required"] = True
    if meaning is not None:
        meta["help"] = meaning
    if choices is not None:
        meta["choices"] = choices
    if bounds is not None:
        meta["range"] = bounds
    return dataclasses.field(default=default, metadata=meta)


def facts(cls: type, name: str) -> Mapping[str, Any]:
    """The facts of field `name` of dataclass `cls`: from the first class in its MRO that declares
    them (a subclass may restate a field's default alone)."""
    for klass in cls.__mro__:
        f = getattr(klass, "__dataclass_fields__", {}).get(name)
        if f is not None and f.metadata:
            return f.metadata
    return {}
