"""Stage 5: G_f on the real references plus the pseudo references, trained from the visual hull or from G_c."""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

import torch

from ...curves import test_probe, write_curve
from ...errors import InputError
from ...gaussians.splats import VIEWER_SH_DEGREE, Splats, export_ply, load_checkpoint, save_checkpoint, to_world
from ...gaussians.stopping import stop_iteration
from ...gaussians.trainer import PseudoViews, train_gaussians
from ...io import read_json
from ...io.exr import read_subbands
from ...io.images import read_image
from ...progress import log
from ...scene.camera import Camera
from ...scene.dataset import Frame, PreparedScene, load_prepared
from ...shape.hull import load_grid
from ...shape.scores import HULL_CUT_LIMIT, hull_cut
from ...workspace import StageRun, Workspace
from ..shared import background_for, ensemble_repair, initial_splats, workspace_repairer
from ..stage import StageEnv
from .settings import FineConfig


def pseudo_schedule(cfg: FineConfig):
    """GaussianObject's: weight start -> end linearly over `pseudo_until` of the steps, then 0."""
    stop = cfg.pseudo_until * cfg.iterations

    def weight(it: int) -> float:
        if it > stop:
            return 0.0
        return cfg.pseudo_weight_start + (cfg.pseudo_weight_end - cfg.pseudo_weight_start) * it / max(stop, 1)

    return weight


def load_pseudo_views(ws: Workspace) -> tuple[list[Frame], list[float]]:
    """The repair stage's pseudo frames (image, and where S ran the mask of where the object may
    be) and their weights."""
    listing = read_json(ws.output("repair", "views"))
    d = ws.stage_dir("repair")  # the listing names its files relative to the stage folder
    frames, weights = [], []
    for v in listing["views"]:
        img = read_subbands(ws.output("repair", "pseudo", f"{v['name'].rsplit('.', 1)[0]}.exr"))["RGB"]
        cam = Camera.from_json(v)
        mask = torch.from_numpy(read_image(d / v["silhouette"])[..., 0].copy()) if "silhouette" in v else None
        frames.append(
            Frame(cam.K, cam.viewmat, cam.width, cam.height, name=v["name"], image=torch.from_numpy(img), mask=mask)
        )
        weights.append(float(v["weight"]))
    return frames, weights


def repaired_again(
    ws: Workspace, splats, frames: list[Frame], background: torch.Tensor, device: torch.device, seed: int
) -> list[Frame]:
    """The pseudo frames with images rendered from `splats` and repaired by this workspace's D and U
    (the repair stage's settings): the next round's pseudo references."""
    repairer = workspace_repairer(ws, device, seed)
    return [dataclasses.replace(f, image=ensemble_repair([splats], f, background, repairer, device)[1]) for f in frames]


def lpips_for_training(cfg: FineConfig, device: torch.device):
    """LPIPS-VGG for the pseudo views (eval's weight search) and what to record: its weight files,
    or why the term is off."""
    if cfg.lpips_weight <= 0:
        return None, {"used": False, "why": "lpips_weight is 0"}
    from ...lpips import LPIPS, LpipsUnavailable

    try:
        fn = LPIPS("vgg", cfg.lpips_weights).to(device)
    except LpipsUnavailable as exc:
        log(f"fine: no LPIPS term ({exc})")
        return None, {"used": False, "why": str(exc)}
    return fn, {"used": True, "weights": fn.sources}


def start_of(cfg: FineConfig, scene: PreparedScene) -> str:
    """Where G_f starts, "hull" or "coarse" (cfg.start with "auto" resolved): the hull where the
    scene has masks and the hull does not cut what the photos show (`shape.scores.hull_cut`; one
    line says so where it does), else G_c."""
    if cfg.start != "auto":
        return cfg.start
    if not scene.has_masks:
        return "coarse"
    try:
        cut = hull_cut(scene.photos, cfg.hull_resolution)
    except InputError:  # the photos' strict hull is empty: the init's tolerant hull decides
        return "hull"
    if cut > HULL_CUT_LIMIT:
        log(
            f"fine: the hull of the other photos leaves out {cut:.1%} of each photo's mask (a mask misses part of the "
            f"object, or the photos crop it) -> G_f starts from G_c, not from the hull"
        )
        return "coarse"
    return "hull"


def starting_splats(ws: Workspace, scene: PreparedScene, cfg: FineConfig, seed: int) -> tuple[Splats, str]:
    """The Gaussians the fine stage trains: the visual-hull init or G_c, and which it is."""
    start = start_of(cfg, scene)
    if start == "hull":
        carved = ws.output("repair", "carved_hull")
        if carved.is_file():
            return initial_splats(scene, cfg, seed, load_grid(carved)), "carved hull"
        return initial_splats(scene, cfg, seed), start
    return load_checkpoint(ws.output("coarse", "model"), scene.norm)[0], start


def run_fine(ws: Workspace, cfg: FineConfig, env: StageEnv, force: bool = False) -> bool:
    return ws.run_staged(
        "fine", cfg, {"seed": env.seed}, force, lambda run: train_fine(run, ws, cfg, env.device, env.seed)
    )


@dataclasses.dataclass
class FineInputs:
    """What the fine stage trains on: the prepared scene, the starting Gaussians and where they come
    from, the pseudo frames and their weights, the background, and the LPIPS term."""

    scene: PreparedScene
    splats: Splats
    start: str
    frames: list[Frame]
    weights: list[float]
    background: torch.Tensor
    lpips_fn: Callable[[torch.Tensor, torch.Tensor], torch.Tensor] | None
    lpips_term: dict

    def pseudo(self, cfg: FineConfig, frames: list[Frame] | None = None) -> PseudoViews:
        return PseudoViews(
            self.frames if frames is None else frames,
            self.weights,
            pseudo_schedule(cfg),
            self.background,
            cfg.pseudo_every,
            self.lpips_fn,
            cfg.lpips_weight,
        )


def fine_inputs(ws: Workspace, cfg: FineConfig, device: torch.device, seed: int) -> FineInputs:
    scene = load_prepared(ws.output("prepare", "prepared"))
    splats, start = starting_splats(ws, scene, cfg, seed)
    frames, weights = load_pseudo_views(ws)
    lpips_fn, lpips_term = lpips_for_training(cfg, device)
    return FineInputs(scene, splats, start, frames, weights, background_for(scene), lpips_fn, lpips_term)


def held_out_stop(ws: Workspace, cfg: FineConfig) -> dict | None:
    """Where G_f stops under the held-out rule: the coarse stage's margin times its pilots' plateau
    (each photo held out in turn, `gaussians.stopping`), of G_f's own iterations. The fine stage
    has no pilots of its own: a photo held out of it is learnt back from the pseudo references,
    which G_c made having seen it (docs/what-we-tried.md). None where either stage's rule is off
    or a time budget sets the length."""
    coarse = ws.manifest("coarse")
    found = coarse.get("stopping") if coarse is not None else None
    if cfg.stop != "held-out" or cfg.max_seconds or coarse is None or not found:
        return None
    c = coarse["config"]  # the coarse stage's StopParams
    return {
        "rule": "coarse pilots",
        "plateau": found["plateau"],
        "margin": c["stop_margin"],
        "stop_at": stop_iteration(found["plateau"], c["stop_margin"], c["stop_min_iterations"], cfg.iterations),
    }


def train_fine(run: StageRun, ws: Workspace, cfg: FineConfig, device: torch.device, seed: int) -> str:
    stop = held_out_stop(ws, cfg)
    if stop is not None:
        cfg = dataclasses.replace(cfg, end_iteration=stop["stop_at"])
        log(
            f"fine: stops at iteration {stop['stop_at']} of {cfg.iterations}, {stop['margin']:g} x {stop['plateau']}, "
            "where the coarse stage's pilots (each photo held out in turn) stopped gaining"
        )
    inputs = fine_inputs(ws, cfg, device, seed)
    scene, splats, start, frames, bg = inputs.scene, inputs.splats, inputs.start, inputs.frames, inputs.background
    torch.manual_seed(seed)
    probe, probe_names = test_probe(ws, scene, cfg, bg, device)
    res, curve, probe_s, offset = None, [], 0.0, 0.0
    for r in range(1, max(1, cfg.rounds) + 1):
        if res is not None:  # a later round: start from the refined model and its repaired renders
            splats = res.splats
            frames = repaired_again(ws, splats, frames, bg, device, seed)
        pseudo = inputs.pseudo(cfg, frames)
        res = train_gaussians(
            splats,
            scene.train,
            cfg,
            device,
            extent=1.0,
            desc="fine" if cfg.rounds == 1 else f"fine round {r}",
            seed=seed + r - 1,
            has_masks=scene.has_masks,
            pseudo=pseudo,
            checkpoint=run.checkpointer("gf" if r == 1 else f"gf{r}"),
            probe=probe,
        )
        # rounds follow each other on one time axis
        curve += [{**p, "seconds": round(p["seconds"] + offset, 3), "round": r} for p in res.curve]
        probe_s += res.probe_seconds
        offset += res.seconds
    assert res is not None  # at least one round
    if probe is not None:
        write_curve(run.output("curve"), dataclasses.replace(res, curve=curve, probe_seconds=probe_s), probe_names)
    save_checkpoint(run.output("model"), res.splats, scene.norm, res.iterations)
    n = export_ply(run.output("ply"), to_world(res.splats, scene.norm), VIEWER_SH_DEGREE)
    run.record.update(
        {
            "num_gaussians": n,
            "iterations": res.iterations,
            "num_pseudo": len(frames),
            "rounds": max(1, cfg.rounds),
            "start": start,
            "lpips_term": inputs.lpips_term,
            "train_seconds": round(res.seconds, 2),
            "final_loss": res.losses[-1],
            "seed": seed,
            "stopping": stop,
        }
    )
    origin = {"hull": "the visual hull", "carved hull": "the carved visual hull"}.get(start, "G_c")
    return f"fine: {n} Gaussians trained from {origin}, {len(frames)} pseudo views, {res.seconds:.1f} s"


# what tools and other packages may use; the rest is this stage's own
__all__ = ["run_fine", "fine_inputs", "FineInputs"]
