"""Plain 3DGS for the pipeline's training time (`wgs baseline`, `wgs all --baseline`): the coarse
stage's trainer and settings for one model, no repair, trained for as long as the stages from
coarse to fine took. Eval scores it beside the method and draws its curve on the error-against-time
plot: what the same time buys without WaveletGaussian."""

from __future__ import annotations

from ...curves import test_probe, write_curve
from ...gaussians.splats import save_checkpoint
from ...gaussians.trainer import train_gaussians
from ...scene.dataset import load_prepared
from ...workspace import StageRun, Workspace
from ..shared import background_for, initial_splats, plain_3dgs_config, recorded_config, stage_times
from ..stage import StageEnv
from .settings import BaselineConfig


def run_baseline(ws: Workspace, cfg: BaselineConfig, env: StageEnv, force: bool = False) -> bool:
    # the budget is the pipeline's training time: coarse is required, the later stages count where they ran
    return ws.run_staged(
        "baseline",
        cfg,
        {"seed": env.seed},
        force,
        lambda run: train_baseline(run, ws, cfg, env),
        requires=("prepare", "coarse"),
    )


def train_baseline(run: StageRun, ws: Workspace, cfg: BaselineConfig, env: StageEnv) -> str:
    scene = load_prepared(ws.output("prepare", "prepared"))
    budget = sum(r["wall_time_s"] for r in stage_times(ws) if r["stage"] != "prepare")
    coarse_s = ws.finished("coarse").get("train_seconds") or budget  # G_c alone, without the other members
    train_cfg = plain_3dgs_config(recorded_config(ws, "coarse"), budget, coarse_s, cfg.headroom)
    probe, names = test_probe(ws, scene, train_cfg, background_for(scene), env.device)
    res = train_gaussians(
        initial_splats(scene, train_cfg, env.seed),
        scene.train,
        train_cfg,
        env.device,
        extent=1.0,
        desc="baseline: plain 3DGS",
        seed=env.seed,
        has_masks=scene.has_masks,
        checkpoint=run.checkpointer("baseline"),
        probe=probe,
    )
    save_checkpoint(run.output("model"), res.splats, scene.norm, res.iterations)
    if probe is not None:
        write_curve(run.output("curve"), res, names)
    run.record.update(
        {"budget_s": round(budget, 1), "train_seconds": round(res.seconds, 1), "iterations": res.iterations}
    )
    return (
        f"baseline: plain 3DGS trained {res.seconds:.0f} s of a {budget:.0f} s budget "
        f"({res.iterations} iterations, {res.splats['means'].shape[0]} Gaussians)"
    )


# what tools and other packages may use; the rest is this stage's own
__all__ = ["run_baseline"]
