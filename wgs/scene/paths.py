"""Paths named inside scene files must stay inside the scene folder."""

from __future__ import annotations

from pathlib import Path

from ..errors import InputError
from ..io.images import IMAGE_EXTS


def safe_join(root: Path, rel: str, source: Path) -> Path:
    """`root / rel`, refusing absolute paths, `..` escapes and symlinks that lead outside `root`.

    `source` is the file that named the path (for the error message).
    """
    if not isinstance(rel, str) or not rel or "\0" in rel or len(rel) > 1024:
        raise InputError(f"invalid file path {str(rel)[:80]!r}", source)
    if Path(rel).is_absolute():
        raise InputError(f"file path {rel!r} is absolute: refusing to read outside the scene folder", source)
    root_r = root.resolve()
    try:
        target = (root / rel).resolve()
    except (OSError, RuntimeError) as exc:  # a symlink loop, a name too long
        raise InputError(f"file path {rel!r} cannot be resolved ({exc})", source) from None
    if not target.is_relative_to(root_r):
        raise InputError(f"file path {rel!r} points outside the scene folder: refused", source)
    return root / rel


def resolve_image(root: Path, rel: str, source: Path) -> Path | None:
    """An image path that may lack its extension (Blender's './train/r_0'); None if missing."""
    p = safe_join(root, rel, source)
    if p.is_file():
        return p
    for ext in IMAGE_EXTS:
        cand = p.with_name(p.name + ext)
        if cand.is_file():
            return safe_join(root, str(Path(rel).parent / cand.name), source)
    return None
