"""`python -m tools.prior corpus|pairs|train`: rebuild the repair prior from fetched repositories.

    python -m tools.prior corpus --mirror /work/.mirror      # extract snapshots, render objects
    python -m tools.prior pairs --budget-min 60              # coarse runs -> (render, ref) pairs
    python -m tools.prior train                              # D and U -> wgs/weights/
    python -m tools.prior volume-pairs && python -m tools.prior train-volume --exclude '*cow*'   # V

Everything is resumable and lives in the cache folder (default ~/.cache/wgs-prior, or $WGS_PRIOR_CACHE).
"""

from __future__ import annotations

import os
from pathlib import Path

import click

from wgs.weights import WEIGHTS, WEIGHTS_S, WEIGHTS_V

DEFAULT_CACHE = Path(os.environ.get("WGS_PRIOR_CACHE", Path.home() / ".cache" / "wgs-prior"))


@click.group()
@click.option(
    "--cache",
    type=click.Path(path_type=Path),
    default=DEFAULT_CACHE,
    show_default=True,
    help="corpus, pairs and training state (outside the repository)",
)
@click.pass_context
def main(ctx: click.Context, cache: Path) -> None:
    """Build the repair prior's corpus and pairs, and train it."""
    ctx.obj = cache


@main.command()
@click.option(
    "--mirror",
    type=click.Path(path_type=Path),
    default=Path("/work/.mirror"),
    show_default=True,
    help="folder of fetched snapshots (owner+name/repo)",
)
@click.option("--procedural", default=60, show_default=True, help="procedural objects (superquadric unions)")
@click.option("--kitbash", default=0, show_default=True, help="procedural box-and-cylinder assemblies (thin parts)")
@click.option("--first-seed", default=0, show_default=True, help="seed (and name) of the first procedural object")
@click.option("--limit", type=int, default=None, help="render at most this many objects")
@click.option("--size", default=128, show_default=True, help="image size in pixels")
@click.option("--workers", default=1, show_default=True, help="one-thread processes")
@click.option(
    "--novel-elevations",
    default=None,
    help="LO,HI degrees of the novel views (default -10,80; the shape corpus takes -85,85)",
)
@click.pass_obj
def corpus(
    cache: Path,
    mirror: Path,
    procedural: int,
    kitbash: int,
    first_seed: int,
    limit: int | None,
    size: int,
    workers: int,
    novel_elevations: str | None,
) -> None:
    """Extract the snapshots and render every object into a Blender-format scene."""
    from .corpus import NOVEL_ELEVATIONS, build_corpus

    try:
        lo, hi = (float(v) for v in novel_elevations.split(",")) if novel_elevations else NOVEL_ELEVATIONS
    except ValueError:
        raise click.BadParameter("two numbers LO,HI", param_hint="--novel-elevations") from None
    done = build_corpus(
        mirror,
        cache,
        procedural,
        limit,
        size,
        first_procedural=first_seed,
        workers=workers,
        n_kitbash=kitbash,
        novel_elevations=(lo, hi),
    )
    click.echo(f"corpus: {len(done)} objects in {cache / 'objects'}")


@main.command()
@click.option("--iterations", default=800, show_default=True, help="coarse iterations per object")
@click.option("--limit", type=int, default=None, help="objects at most")
@click.option("--budget-min", type=float, default=None, help="stop after this many minutes (rerun continues)")
@click.option("--workers", default=1, show_default=True, help="one-thread processes")
@click.pass_obj
def pairs(cache: Path, iterations: int, limit: int | None, budget_min: float | None, workers: int) -> None:
    """Coarse 3DGS per object on sparse views; its renders at novel poses paired with the truth."""
    from .pairs import build_pairs

    n = build_pairs(cache, {"iterations": iterations}, limit, None if budget_min is None else budget_min * 60, workers)
    click.echo(f"pairs: {n} new objects in {cache / 'pairs'}")


@main.command()
@click.option(
    "--pack",
    type=click.Path(path_type=Path),
    default=None,
    help="a training pack (default: pack the cache's pairs into CACHE/pack.npz first)",
)
@click.option("--out", type=click.Path(path_type=Path), default=None, help="default: the package's weights/")
@click.option("--device", default="auto", show_default=True, help="auto | cpu | cuda")
@click.option("--d-steps", type=int, default=None, help="D training steps")
@click.option("--u-steps", type=int, default=None, help="U training steps")
@click.option("--d-lr", type=float, default=None, help="D's peak learning rate")
@click.option(
    "--init",
    type=click.Path(path_type=Path, file_okay=False),
    default=None,
    help="start from this prior's D and U (e.g. wgs/weights) instead of from scratch",
)
@click.option("--pack-only", is_flag=True, help="write the pack and stop (to carry it to a GPU machine)")
@click.pass_obj
def train(
    cache: Path,
    pack: Path | None,
    out: Path | None,
    device: str,
    d_steps: int | None,
    u_steps: int | None,
    d_lr: float | None,
    init: Path | None,
    pack_only: bool,
) -> None:
    """Pretrain D and U on the pairs (held-out objects measure generalisation). D's training state is
    kept in the cache: a rerun with the same settings continues it."""
    import json

    import torch

    from .train import PriorConfig, pack_pairs, train_prior

    provenance = None
    if pack is None:
        pack = cache / "pack.npz"
        provenance = pack_pairs(cache / "pairs", pack)
        from .corpus import procedural_objects

        corpus_doc = json.loads((cache / "corpus.json").read_text())
        listed = {o["name"]: o for o in corpus_doc["objects"]}
        provenance["snapshots"] = corpus_doc.get("snapshots", {})
        used = sorted({n.rsplit("_v", 1)[0] for n in provenance["objects"]})
        for n in used:  # procedural objects made elsewhere (another machine's cache) are known by their seed
            kind, _, seed = n.rpartition("-")
            if n not in listed and kind in ("procedural", "kitbash") and seed.isdigit():
                listed[n] = procedural_objects(1, int(seed), kind)[0]
        provenance["sources"] = [
            {k: listed[n].get(k) for k in ("name", "repo", "path", "licence", "kind", "seed")}
            for n in used
            if n in listed
        ]
        (cache / "pack.json").write_text(json.dumps(provenance, indent=1))
        click.echo(f"pack: {provenance['pairs']} pairs from {len(provenance['objects'])} objects -> {pack}")
        if pack_only:
            return
    elif (pack.parent / "pack.json").is_file():
        provenance = json.loads((pack.parent / "pack.json").read_text())
    dev = torch.device(
        "cuda" if device == "auto" and torch.cuda.is_available() else ("cpu" if device == "auto" else device)
    )
    cfg = PriorConfig()
    for name, value in (("d_steps", d_steps), ("u_steps", u_steps), ("d_lr", d_lr)):
        if value is not None:
            setattr(cfg, name, value)
    rec = train_prior(
        pack, out or WEIGHTS, cfg, dev, provenance, log=lambda m: click.echo(m), init=init, state_dir=cache
    )
    click.echo(f"prior: D {rec['d_seconds']} s, U {rec['u_seconds']} s on {dev}")


@main.command()
@click.option("--pack", type=click.Path(path_type=Path), required=True, help="a training pack")
@click.option("--fractions", default="0.25,0.5,1.0", show_default=True, help="shares of the training objects")
@click.option("--d-steps", default=4000, show_default=True, help="D training steps per point")
@click.option("--device", default="auto", show_default=True, help="auto | cpu | cuda")
@click.option("--out", type=click.Path(path_type=Path), default=None, help="write the rows as JSON here")
def curve(pack: Path, fractions: str, d_steps: int, device: str, out: Path | None) -> None:
    """Held-out repair gain of D against corpus size (same held-out objects for every point)."""
    import json

    import torch

    from .train import PriorConfig, corpus_curve

    dev = torch.device(
        "cuda" if device == "auto" and torch.cuda.is_available() else ("cpu" if device == "auto" else device)
    )
    cfg = PriorConfig(d_steps=d_steps)
    rows = corpus_curve(pack, [float(f) for f in fractions.split(",")], cfg, dev, log=lambda m: click.echo(m))
    if out is not None:
        out.write_text(json.dumps(rows, indent=1))


def _device(name: str):
    import torch

    return torch.device("cuda" if name == "auto" and torch.cuda.is_available() else ("cpu" if name == "auto" else name))


@main.command("train-shape")
@click.option("--out", type=click.Path(path_type=Path), default=None, help="default: the package's weights/S")
@click.option("--steps", type=int, default=None, help="training steps")
@click.option("--work-size", type=int, default=None, help="S's working size in px (default: the network config's)")
@click.option("--levels", type=int, default=None, help="S's downsamplings (default: the network config's)")
@click.option("--device", default="auto", show_default=True, help="auto | cpu | cuda")
@click.pass_obj
def train_shape(
    cache: Path, out: Path | None, steps: int | None, work_size: int | None, levels: int | None, device: str
) -> None:
    """Train the silhouette model S on the pairs' hull channels (held-out objects measure it)."""
    import json

    from wgs.models.storage import save_model

    from .train_shape import ShapeTrainConfig, load_shape_pairs, train_silhouette

    cfg = ShapeTrainConfig()
    if steps is not None:
        cfg.steps = steps
    if work_size is not None:
        cfg.net.work_size = work_size
    if levels is not None:
        cfg.net.levels = levels
    data = load_shape_pairs(cache / "pairs", cfg.net.work_size)
    click.echo(
        f"S: {len(data['target'])} pairs from {len(data['names'])} pair files, {int(data['holdout'].sum())} held out"
    )
    model, curve = train_silhouette(data, cfg, _device(device), log=click.echo)
    out = out or WEIGHTS_S
    save_model(out, model)
    held = sorted({data["names"][int(i)] for i in data["object"][data["holdout"]].unique()})
    (out / "provenance.json").write_text(
        json.dumps(
            {
                "pairs": int((~data["holdout"]).sum()),
                "objects": data["names"],
                "holdout_objects": held,
                "curve": curve,
                "command": f"python -m tools.prior --cache CACHE train-shape --steps {cfg.steps} "
                f"--work-size {cfg.net.work_size} --levels {cfg.net.levels}",
            },
            indent=1,
        )
    )
    click.echo(f"S: {curve['seconds']} s -> {out}")


@main.command("shape-curve")
@click.option("--fractions", default="0.25,0.5,1.0", show_default=True, help="shares of the training objects")
@click.option("--steps", default=1500, show_default=True, help="training steps per point")
@click.option("--device", default="auto", show_default=True, help="auto | cpu | cuda")
@click.option("--out", type=click.Path(path_type=Path), default=None, help="write the rows as JSON here")
@click.pass_obj
def shape_curve_cmd(cache: Path, fractions: str, steps: int, device: str, out: Path | None) -> None:
    """Held-out silhouette IoU of S against corpus size (same held-out objects for every point)."""
    import json

    from .train_shape import ShapeTrainConfig, load_shape_pairs, shape_curve

    cfg = ShapeTrainConfig(steps=steps)
    rows = shape_curve(
        load_shape_pairs(cache / "pairs", cfg.net.work_size),
        [float(f) for f in fractions.split(",")],
        cfg,
        _device(device),
        log=click.echo,
    )
    if out is not None:
        out.write_text(json.dumps(rows, indent=1))


@main.command("volume-pairs")
@click.option("--subsets", default=16, show_default=True, help="view subsets per object")
@click.option("--resolution", default=32, show_default=True, help="cells per side of V's cube")
@click.option("--limit", type=int, default=None, help="the first this many corpus objects")
@click.option("--workers", default=1, show_default=True, help="one-thread processes")
@click.pass_obj
def volume_pairs(cache: Path, subsets: int, resolution: int, limit: int | None, workers: int) -> None:
    """(few-view hull, many-view hull) cubes of the rendered corpus objects, for V."""
    from .volume_pairs import build_volume_pairs

    made = build_volume_pairs(cache, subsets, resolution, limit, workers)
    click.echo(f"volume pairs: {made} new object files in {cache / 'volume_pairs'}")


@main.command("train-volume")
@click.option("--out", type=click.Path(path_type=Path), default=None, help="default: the package's weights/V")
@click.option("--steps", type=int, default=None, help="training steps")
@click.option("--exclude", multiple=True, help="object name pattern left out (a shape a benchmark measures)")
@click.option("--device", default="auto", show_default=True, help="auto | cpu | cuda")
@click.pass_obj
def train_volume_cmd(cache: Path, out: Path | None, steps: int | None, exclude: tuple[str, ...], device: str) -> None:
    """Train the volume model V on the volume pairs (held-out objects measure it)."""
    import json

    from wgs.models.storage import save_model

    from .train_volume import VolumeTrainConfig, load_volume_pairs, train_volume

    cfg = VolumeTrainConfig()
    if steps is not None:
        cfg.steps = steps
    data = load_volume_pairs(cache / "volume_pairs", exclude)
    click.echo(f"V: {len(data['y'])} cubes from {len(data['names'])} objects, {int(data['holdout'].sum())} held out")
    model, curve = train_volume(data, cfg, _device(device), log=click.echo)
    out = out or WEIGHTS_V
    save_model(out, model)
    excluded = " ".join(f"--exclude '{p}'" for p in exclude)
    (out / "provenance.json").write_text(
        json.dumps(
            {
                "cubes": int((~data["holdout"]).sum()),
                "objects": data["names"],
                "excluded": list(exclude),
                "curve": curve,
                "command": f"python -m tools.prior --cache CACHE volume-pairs && python -m tools.prior --cache CACHE "
                f"train-volume --steps {cfg.steps} {excluded}".strip(),
            },
            indent=1,
        )
    )
    click.echo(f"V: {curve['seconds']} s -> {out}")


if __name__ == "__main__":
    main()
