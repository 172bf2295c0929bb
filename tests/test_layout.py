"""The house plan, checked: stages import the shared stage module and the layers below, never
each other (issue 14)."""

import ast
from pathlib import Path

STAGES = Path(__file__).resolve().parents[1] / "wgs" / "stages"


def imported_modules(path: Path) -> set[str]:
    """Relative module names a file imports (`from .x import y` -> "x", `from . import x` -> "x")."""
    out = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom) and node.level == 1:
            if node.module:
                out.add(node.module.split(".")[0])
            else:
                out.update(a.name for a in node.names)
    return out


def test_no_stage_imports_another_stage():
    stage_modules = {p.stem for p in STAGES.glob("*.py")} - {"__init__", "shared"}
    assert {"s1_coarse", "s6_eval", "render_views"} <= stage_modules
    for p in STAGES.glob("*.py"):
        siblings = imported_modules(p) & stage_modules - {p.stem}
        assert not siblings, f"{p.name} imports {sorted(siblings)}: move what they share to stages/shared.py"
