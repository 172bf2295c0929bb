"""The house plan, checked: stages import the shared stage module and the layers below, never
each other."""

import ast
import fnmatch
import re
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


TOOLS = WGS.parent / "tools"  # benchmarks and the kill loop: beside the package, not in the wheel


def import_graph(with_tools: bool = False) -> dict[str, set[str]]:
    """{module: the modules of wgs (and, `with_tools`, of tools/) it imports}, less each stage's
    settings reaching its own run module on first use (`run_on_first_use`)."""
    paths = [*WGS.rglob("*.py"), *(TOOLS.rglob("*.py") if with_tools else ())]
    files = {module_name(p): p for p in paths}
    return {m: imports_of(p, set(files)) - run_on_first_use(m, p) for m, p in files.items()}


def run_on_first_use(module: str, path: Path) -> set[str]:
    """A stage's settings (config layer) name its run function (stages layer) in its `Stage` row
    through a `run` function that imports the stage's own `run` module when called, and so loads
    the library only when the stage runs: that one import, inside that function, is the one edge
    that points up (docs/architecture.md)."""
    if not (module.startswith("wgs.stages.") and module.endswith(".settings")):
        return set()
    own_run = module.removesuffix(".settings") + ".run"
    tree = ast.parse(path.read_text())
    for node in tree.body:
        assert not (isinstance(node, ast.ImportFrom) and node.module == "run"), f"{module}: run imported on top"
    inside = [n for f in tree.body if isinstance(f, ast.FunctionDef) and f.name == "run" for n in ast.walk(f)]
    names = [
        a.name for n in inside if isinstance(n, ast.ImportFrom) and n.level == 1 and n.module == "run" for a in n.names
    ]
    return {own_run, *(f"{own_run}.{name}" for name in names)} if names else set()


def test_no_stage_imports_another_stage():
    """A stage's modules import another stage's settings at most (the config layer), never its run."""
    graph = import_graph()
    stage_of = {m: m.split(".")[2] for m in graph if m.startswith("wgs.stages.") and m.count(".") >= 2}
    stages = {name for m, name in stage_of.items() if m.count(".") >= 3}  # the packages: stages/<name>/
    assert {"prepare", "coarse", "eval", "baseline"} <= stages
    for m, stage in stage_of.items():
        if stage not in stages:
            continue
        others = {stage_of[d] for d in graph[m] if d in stage_of and not d.endswith(".settings")} & stages - {stage}
        assert not others, f"{m} imports {sorted(others)}: move what they share to stages/shared.py"


def test_lower_layers_know_no_workspace():
    graph = import_graph()
    lower = [m for m in graph if m.split(".")[1:2] in (["scene"], ["gaussians"], ["wavelet"], ["models"], ["io"])]
    assert len(lower) > 20
    for m in lower:
        assert "wgs.workspace" not in graph[m], f"{m} imports wgs.workspace: take paths, use wgs.io"


def page_layers() -> list[tuple[str, tuple[str, ...]]]:
    """docs/architecture.md's table of layers, lowest first: (layer, the top-level names of its
    modules and packages, as the table's first backquoted names give them)."""
    page = (WGS.parent / "docs" / "architecture.md").read_text()
    table = page.split("| layer | modules | what it knows |")[1].split("\n\n")[0].strip().splitlines()[1:]
    rows = []
    for line in table:
        layer, modules = (c.strip() for c in line.strip().strip("|").split("|")[:2])
        names = re.findall(r"`([^`]+)`", modules.split("(")[0])  # what follows in brackets are files within
        rows.append((layer, tuple(n.removesuffix("/").removesuffix(".py") for n in names)))
    return rows


LAYERS = page_layers()


def layer_of(module: str) -> int | None:
    """The layer whose row names the module: by its path (`stages/*/settings`) before its top-level
    name (`stages`)."""
    path = "/".join(module.split(".")[1:]) or "__init__"  # "wgs" itself: its __init__
    for by_path in (True, False):
        for i, (_, names) in enumerate(LAYERS):
            if by_path and any("/" in n and fnmatch.fnmatchcase(path, n) for n in names):
                return i
            if not by_path and path.split("/")[0] in names:
                return i
    return None


def test_the_page_names_the_layers_and_every_module_is_in_one():
    assert [layer for layer, _ in LAYERS] == [
        "utilities", "library", "config", "training", "workspace", "stages", "orchestration", "commands", "tools"
    ]  # fmt: skip
    homeless = sorted(m for m in import_graph() if layer_of(m) is None)
    assert not homeless, f"in no layer of docs/architecture.md: {homeless}"


def test_imports_point_down():
    """Every module imports its own layer and those below it, as docs/architecture.md's table
    says: no estimate that reaches into a stage, no library piece that knows the workspace."""
    graph = import_graph()
    for m, deps in graph.items():
        mine = layer_of(m)
        above = sorted(d for d in deps if layer_of(d) > mine)
        assert not above, f"{m} ({LAYERS[mine][0]}) imports {above}, above its layer"
    assert layer_of("wgs.scene.prepare") == 1 and layer_of("wgs.estimate") == 4 and layer_of("wgs.batch") == 6
    assert layer_of("wgs.stages.coarse.settings") == layer_of("wgs.stages.registry") == layer_of("wgs.config") == 2
    assert layer_of("wgs.stages.coarse.run") == layer_of("wgs.stages.shared") == layer_of("wgs.stages") == 5


def test_every_registry_stage_runs_through_one_signature():
    """Each stage's row names its run function (not a string) with one signature, and the
    function it calls is its own run module's `run_<name>`, of the same signature."""
    import importlib
    import inspect

    from wgs.stages.registry import REGISTRY

    for stage in REGISTRY:
        assert stage.run.__module__ == f"wgs.stages.{stage.name}.settings", stage.name
        params = list(inspect.signature(stage.run).parameters)
        assert params == ["ws", "cfg", "env", "force"], f"{stage.name}: {params}"
        own = getattr(importlib.import_module(f"wgs.stages.{stage.name}.run"), f"run_{stage.name}")
        assert list(inspect.signature(own).parameters) == params, stage.name


def test_orchestration_spells_no_stage_order():
    # orchestration, the estimate, the workspace and the commands loop over the registry: no stage's
    # own module is imported by name there
    graph = import_graph()
    for module in ("wgs.pipeline", "wgs.ablation", "wgs.estimate", "wgs.workspace", "wgs.cli.stages", "wgs.config"):
        named = {d for d in graph[module] if d.startswith("wgs.stages.") and d.count(".") >= 3}
        assert not named, f"{module} imports {sorted(named)}: go through wgs.stages.registry"


def test_training_sits_between_the_networks_and_their_callers():
    # models (networks, sampling, the repair) < training (the loop, objectives, the per-object
    # fine-tune) < stages and prior; the loop itself takes its checkpoint as a protocol (saved state and
    # interrupts, `wgs.resume`, are a utility the per-object trainers wire in)
    graph = import_graph(with_tools=True)
    for m, deps in graph.items():
        if m.startswith("wgs.models"):
            assert not {d for d in deps if d.startswith("wgs.training")}, f"{m} imports the training layer"
        if m.startswith("wgs.training"):
            upper = {d for d in deps if d.startswith("tools.") or layer_of(d) > layer_of(m)}
            assert not upper, f"{m} imports {sorted(upper)}"
    assert "wgs.resume" not in graph["wgs.training.loop"]
    assert "wgs.training.per_object" in graph["wgs.stages.finetune.run"]
    assert "wgs.training.loop" in graph["wgs.training.denoiser"]
    assert "wgs.training.denoiser" in graph["tools.prior.train"]


def test_orchestration_and_stages_know_no_click():
    # the CLI is click only: orchestration takes wgs.context.RunOptions, a plain object
    orchestration = next(names for layer, names in LAYERS if layer == "orchestration")
    assert "batch" in orchestration
    for rel in (*(f"{name}.py" if name != "viewer" else name for name in orchestration), "stages"):
        for p in [WGS / rel] if rel.endswith(".py") else sorted((WGS / rel).rglob("*.py")):
            tops = set()
            for node in ast.walk(ast.parse(p.read_text())):
                if isinstance(node, ast.Import):
                    tops.update(a.name.split(".")[0] for a in node.names)
                elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                    tops.add(node.module.split(".")[0])
            assert "click" not in tops, f"{p.relative_to(WGS.parent)} imports click"


def test_bench_and_stress_tools_stay_apart():
    # `python -m tools.bench` / `tools.stress` are tools around the product, outside the package (and
    # so the wheel): nothing of it imports them
    graph = import_graph(with_tools=True)
    tools = {m for m in graph if m.split(".")[0] == "tools"}
    assert {"tools.bench", "tools.stress"} <= tools
    for m, deps in graph.items():
        assert m in tools or not deps & tools, f"{m} imports {sorted(deps & tools)}"
    assert not list(WGS.glob("bench*.py")) and not list(WGS.glob("stress*.py"))


def test_the_tools_commands_are_click_as_wgs_is():
    for main in (TOOLS / "bench.py", TOOLS / "stress.py", TOOLS / "prior" / "__main__.py"):
        tops = {m.split(".")[0] for m in imported_top_modules(main)}
        assert "click" in tops and "argparse" not in tops, f"{main.relative_to(WGS.parent)}: {sorted(tops)}"


def imported_top_modules(path: Path) -> set[str]:
    """Absolute module names a file imports anywhere in it."""
    out = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            out.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            out.add(node.module)
    return out


def run_module_public_names() -> dict[str, set[str]]:
    """{"wgs.stages.<name>.run": the names its `__all__` offers}, for every stage."""
    out = {}
    for p in sorted(STAGES.glob("*/run.py")):
        names = None
        for node in ast.parse(p.read_text()).body:
            if isinstance(node, ast.Assign) and any(getattr(t, "id", "") == "__all__" for t in node.targets):
                names = {ast.literal_eval(e) for e in node.value.elts}  # type: ignore[attr-defined]
        assert names, f"{p.relative_to(WGS.parent)} declares no __all__ (what tools may use of it)"
        out[module_name(p)] = names
    return out


def stage_names_used(path: Path, runs: set[str]) -> dict[str, set[str]]:
    """{stage run module: the names a file takes from it} -- `from M import x` and `import M as m`
    then `m.x` alike."""
    used: dict[str, set[str]] = {}
    aliases: dict[str, str] = {}
    tree = ast.parse(path.read_text())
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and node.module in runs:
            used.setdefault(node.module, set()).update(a.name for a in node.names)
        elif isinstance(node, ast.Import):
            aliases.update({a.asname or a.name: a.name for a in node.names if a.name in runs})
    for node in ast.walk(tree):
        if isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name) and node.value.id in aliases:
            used.setdefault(aliases[node.value.id], set()).add(node.attr)
    return used


def test_tools_reach_a_stage_only_through_its_public_names():
    # a stage's run module is its own; tools (bench, experiments, the prior's corpus) take from it
    # only what its __all__ offers, so that a stage can change inside without breaking them
    public = run_module_public_names()
    assert len(public) == len(list(STAGES.glob("*/settings.py")))
    for p in TOOLS.rglob("*.py"):
        for module, names in stage_names_used(p, set(public)).items():
            extra = names - public[module]
            assert not extra, f"{p.relative_to(WGS.parent)} takes {sorted(extra)} from {module}, not in its __all__"


def test_no_import_cycle():
    graph, state = import_graph(), {}

    def visit(m: str, path: list[str]) -> None:
        state[m] = "open"
        for d in sorted(graph[m]):
            assert state.get(d) != "open", "import cycle: " + " -> ".join(path[path.index(d) :] + [d])
            if d not in state:
                visit(d, path + [d])
        state[m] = "done"

    for m in sorted(graph):
        if m not in state:
            visit(m, [m])


def test_the_stages_are_listed_once():
    import re

    from wgs.cli import cli
    from wgs.stages.registry import METHOD, REGISTRY

    names = [s.name for s in REGISTRY]
    assert METHOD[-1] == "fine" and "eval" not in METHOD and "baseline" not in METHOD
    for i, s in enumerate(REGISTRY):
        assert set(s.upstream) <= set(names[:i]), f"{s.name} reads a stage that runs after it"
        assert s.command in cli.commands
    # a folder named like its stage is no second fact; prepare's "scene" is also the word for the
    # scene in records (run.json, results.json): there only a path joined onto it counts
    folders = re.compile(
        "|".join(
            re.escape(f'"{s.folder}"') if s.folder != "scene" else r'/\s*"scene"\s*/'
            for s in REGISTRY
            if s.folder != s.name
        )
    )
    for p in WGS.rglob("*.py"):
        if p.name != "settings.py":
            assert not folders.search(p.read_text()), f"{p.name} spells a stage folder: use STAGE_DIRS"


def test_cli_options_are_the_config_fields():
    """Every option of a stage command (and of `wgs all`) is a config field's: its help is the
    field's meaning, its choices and range are the field's (`fields.option`), it leaves the default
    to the config (None) and states the config's default; no such command has an option that no
    field declares, other than the shared ones."""
    import re

    import click

    from wgs.cli import cli
    from wgs.config import CHOICES, RANGES, STAGES
    from wgs.fields import facts
    from wgs.stages.registry import REGISTRY

    shared = {"force", "preset", "ws_override", "scene", "budget", "force_repair", "baseline", "help"}

    checked = set()
    for name in [s.command for s in REGISTRY] + ["all"]:
        command = cli.commands[name]
        classes = [STAGES[name.replace("-", "_")]] if name != "all" else list(STAGES.values())
        for param in command.params:
            owners = [c for c in classes if param.name in c.__dataclass_fields__]
            if not owners:
                assert param.name in shared, f"wgs {name} --{param.name} is no config field's"
                continue
            default = getattr(owners[0], param.name)
            meaning = facts(owners[0], param.name).get("help")
            assert meaning and (param.help or "").startswith(meaning), (name, param.name, param.help)
            assert CHOICES.get(param.name) == facts(owners[0], param.name).get("choices"), (name, param.name)
            assert RANGES.get(param.name) == facts(owners[0], param.name).get("range"), (name, param.name)
            assert param.default is None, (name, param.name)
            if param.name in CHOICES:
                assert tuple(param.type.choices) == CHOICES[param.name], (name, param.name)
            if param.name in RANGES:
                assert isinstance(param.type, click.IntRange | click.FloatRange), (name, param.name)
                assert (param.type.min, param.type.max) == RANGES[param.name], (name, param.name)
            m = re.search(r"\(default ([^\s;)]+)\)", param.help or "")
            if default is None:
                assert m is None, (name, param.name)
            else:
                stated = str(default).lower() if isinstance(default, bool) else str(default)
                assert m is not None and m.group(1) == stated, (name, param.name, param.help)
            checked.add((name, param.name))
    assert len(checked) >= 30 and ("all", "ensemble") in checked and ("coarse", "sh_degree") in checked


def test_a_config_range_is_enforced_for_every_command():
    """`wgs all` validates what `wgs coarse` does: the range lives in the config, not in one command."""
    import pytest

    from wgs.config import resolve
    from wgs.errors import InputError

    for table, key, bad in (
        ("coarse", "sh_degree", 4),
        ("fine", "sh_degree", -1),
        ("prepare", "views", 1),
        ("prepare", "downscale", 0),
    ):
        with pytest.raises(InputError, match=key):
            resolve(table, file_cfg={table: {key: bad}})


def test_readers_find_outputs_through_the_registry():
    """No module joins a path onto another stage's folder: what a stage writes for others is declared
    in `config.REGISTRY` (`Stage.outputs`) and found with `Workspace.output`."""
    import re

    joined = re.compile(r"stage_dir\([^)]*\)\s*/|STAGE_DIRS\[[^\]]*\]\s*/\s*[\"A-Z]")
    for p in WGS.rglob("*.py"):
        if p.name != "workspace.py":
            hits = joined.findall(p.read_text())
            assert not hits, f"{p.relative_to(WGS.parent)} spells a stage's path: {hits}"


def test_every_option_of_every_command_is_a_fields_option():
    """No hand-written option: every option of the group and of every command (tools included)
    takes its help, and its choices or range, from a settings dataclass's field (`fields.option`)."""
    import dataclasses
    import inspect
    import sys

    import click

    from wgs.cli import cli
    from wgs.config import RUN_TABLES, STAGES
    from wgs.fields import facts

    settings = list(STAGES.values()) + list(RUN_TABLES.values())
    for name, module in list(sys.modules.items()):
        if name.startswith("wgs.cli."):
            settings += [c for _, c in inspect.getmembers(module, dataclasses.is_dataclass) if isinstance(c, type)]
    commands = [("wgs", cli)] + [(f"wgs {n}", c) for n, c in cli.commands.items()]
    seen = 0
    for where, command in commands:
        for param in command.params:
            if not isinstance(param, click.Option) or param.name in ("help", "version"):
                continue
            name = "workspace" if param.name == "ws_override" else param.name  # -w after the command
            owners = [c for c in settings if name in {f.name for f in dataclasses.fields(c)}]
            meanings = [facts(c, name).get("help") for c in owners]
            assert any(m and (param.help or "").startswith(m) for m in meanings), f"{where} --{name}: {param.help!r}"
            for c in owners:
                if facts(c, name).get("choices") is not None and isinstance(param.type, click.Choice):
                    assert tuple(param.type.choices) == facts(c, name)["choices"], (where, name)
            seen += 1
    assert seen > 100 and len(commands) >= 16


def stage_own_fields() -> dict[str, set[str]]:
    """Each stage's own settings fields: those its settings class declares, not a library
    parameter class it extends (`TrainConfig`, `MaskParams`, ...)."""
    from wgs.stages.registry import REGISTRY

    out = {}
    for s in REGISTRY:
        inherited = {f for base in s.settings.__mro__[1:] for f in getattr(base, "__dataclass_fields__", {})}
        out[s.name] = set(s.settings.__dataclass_fields__) - inherited
    return out


def strings_and_attributes(path: Path) -> tuple[set[str], set[str]]:
    """The string constants a file holds and the attribute names it reads."""
    tree = ast.parse(path.read_text())
    strings = {n.value for n in ast.walk(tree) if isinstance(n, ast.Constant) and isinstance(n.value, str)}
    return strings, {n.attr for n in ast.walk(tree) if isinstance(n, ast.Attribute)}


def test_a_stages_options_and_cost_are_stated_in_its_home():
    """The commands take a stage's options from its `Stage` row (`options`, `all_options`), and the
    estimate takes its cost from the row's `cost`: no command module names a stage's option, and
    neither the estimate nor the shared cost pieces name a stage or read a stage's own setting."""
    from wgs.stages.registry import REGISTRY

    options = {o for s in REGISTRY for o in (*s.options, *s.all_options)}
    assert {"ensemble", "views", "strategy", "lpips_weights"} <= options
    for p in sorted((WGS / "cli").glob("*.py")):
        named = strings_and_attributes(p)[0] & options
        assert not named, f"{p.relative_to(WGS.parent)} lists options of a stage: {sorted(named)} (Stage.options)"
    own = set().union(*stage_own_fields().values())
    assert {"ensemble", "rounds", "num_views", "strategy", "prior_steps"} <= own
    for rel in ("estimate.py", "cost.py"):
        strings, attributes = strings_and_attributes(WGS / rel)
        assert not strings & {s.name for s in REGISTRY}, (
            f"{rel} names a stage: {sorted(strings & {s.name for s in REGISTRY})}"
        )
        assert not attributes & own, f"{rel} reads a stage's own setting: {sorted(attributes & own)} (Stage.cost)"
