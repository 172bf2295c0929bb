"""The house plan, checked: stages import the shared stage module and the layers below, never
each other."""

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


WGS = STAGES.parent


def module_name(path: Path) -> str:
    parts = list(path.relative_to(WGS.parent).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def imports_of(path: Path, modules: set[str]) -> set[str]:
    """The wgs modules a file imports anywhere in it (function-level imports included)."""
    name = module_name(path)
    package = name.split(".") if path.name == "__init__.py" else name.split(".")[:-1]
    out = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            out.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = ".".join(package[: len(package) - node.level + 1]) if node.level else ""
            full = ".".join(p for p in (base, node.module or "") if p)
            out.add(full)
            out.update(f"{full}.{a.name}" for a in node.names)
    return (out & modules) - {name}


def import_graph() -> dict[str, set[str]]:
    files = {module_name(p): p for p in WGS.rglob("*.py")}
    return {m: imports_of(p, set(files)) for m, p in files.items()}


def test_lower_layers_know_no_workspace():
    graph = import_graph()
    lower = [m for m in graph if m.split(".")[1:2] in (["scene"], ["gaussians"], ["wavelet"], ["models"], ["io"])]
    assert len(lower) > 20
    for m in lower:
        assert "wgs.workspace" not in graph[m], f"{m} imports wgs.workspace: take paths, use wgs.io"


def test_every_registry_stage_runs_through_one_signature():
    import inspect

    from wgs.config import REGISTRY
    from wgs.stages import stage_runner

    for stage in REGISTRY:
        params = list(inspect.signature(stage_runner(stage.name)).parameters)
        assert params == ["ws", "cfg", "env", "force"], f"{stage.runner}: {params}"


def test_orchestration_spells_no_stage_order():
    # pipeline.py and ablation.py loop over the registry; no stage module is imported by name there
    for rel in ("pipeline.py", "ablation.py"):
        src = (WGS / rel).read_text()
        assert "wgs.stages.s" not in src and ".stages.s" not in src.replace(".stages.shared", ""), rel


def test_training_sits_between_the_networks_and_their_callers():
    # models (networks, sampling, the repair) < training (the loop, objectives) < stages and prior
    graph = import_graph()
    for m, deps in graph.items():
        if m.startswith("wgs.models"):
            assert not {d for d in deps if d.startswith("wgs.training")}, f"{m} imports the training layer"
        if m.startswith("wgs.training"):
            upper = {d for d in deps if d.split(".")[1] in ("stages", "prior", "workspace", "resume", "pipeline")}
            assert not upper, f"{m} imports {sorted(upper)}"
    assert {"wgs.training.loop"} <= graph["wgs.stages.s3_finetune"] | graph["wgs.training.denoiser"]
    assert "wgs.training.denoiser" in graph["wgs.prior.train"]


def test_orchestration_and_stages_know_no_click():
    # the CLI is click only: orchestration takes wgs.context.Ctx, a plain object
    for rel in ("pipeline.py", "ablation.py", "context.py", "stages"):
        for p in [WGS / rel] if rel.endswith(".py") else sorted((WGS / rel).glob("*.py")):
            tops = set()
            for node in ast.walk(ast.parse(p.read_text())):
                if isinstance(node, ast.Import):
                    tops.update(a.name.split(".")[0] for a in node.names)
                elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                    tops.add(node.module.split(".")[0])
            assert "click" not in tops, f"{p.relative_to(WGS.parent)} imports click"


def test_bench_and_stress_tools_stay_apart():
    # `python -m wgs.bench` / `wgs.stress` are tools around the product: nothing of it imports them
    graph = import_graph()
    tools = {"wgs.bench", "wgs.stress"}
    assert tools <= set(graph)
    for m, deps in graph.items():
        assert m in tools or not deps & tools, f"{m} imports {sorted(deps & tools)}"


def test_no_import_cycle():
    graph, state = import_graph(), {}

    def visit(m: str, path: list[str]) -> None:
        state[m] = "open"
        for d in sorted(graph[m]):
            assert state.get(d) != "open", "import cycle: " + " -> ".join(path[path.index(d):] + [d])
            if d not in state:
                visit(d, path + [d])
        state[m] = "done"

    for m in sorted(graph):
        if m not in state:
            visit(m, [m])


def test_the_stages_are_listed_once():
    import re

    from wgs.cli import cli
    from wgs.config import METHOD, REGISTRY, STAGES
    from wgs.workspace import COMMANDS, STAGE_DIRS, UPSTREAM

    names = [s.name for s in REGISTRY]
    assert list(STAGE_DIRS) == list(UPSTREAM) == list(COMMANDS) == names
    assert list(STAGES) == [s.table for s in REGISTRY] and METHOD[-1] == "fine" and "eval" not in METHOD
    for i, s in enumerate(REGISTRY):
        assert set(s.upstream) <= set(names[:i]), f"{s.name} reads a stage that runs after it"
        assert s.command in cli.commands
    folders = re.compile("|".join(re.escape(f'"{s.folder}"') for s in REGISTRY if s.folder != s.name))
    for p in WGS.rglob("*.py"):
        if p.name != "config.py":
            assert not folders.search(p.read_text()), f"{p.name} spells a stage folder: use STAGE_DIRS"


def test_cli_help_states_the_config_defaults():
    """Every "default X" in a stage command's option help is the config's default for that option."""
    import re

    from wgs.cli import cli
    from wgs.config import REGISTRY, STAGES

    stated = 0
    for name in [s.command for s in REGISTRY] + ["all"]:
        command = cli.commands[name]
        classes = [STAGES[name.replace("-", "_")]] if name != "all" else list(STAGES.values())
        for param in command.params:
            m = re.search(r"default ([^\s;)]+)", getattr(param, "help", None) or "")
            owners = [c for c in classes if param.name in c.__dataclass_fields__]
            if m is None or not owners:
                continue
            stated += 1
            assert m.group(1).rstrip(".") == str(getattr(owners[0], param.name)), (name, param.name)
    assert stated >= 4  # --ensemble (coarse, all), --n-regions, --coverage, --levels
