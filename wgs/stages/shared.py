"""What the stages share: their output file names, the background renders are composited on,
the initial Gaussians, the subbands written beside renders. Stages import this module and the
layers below it, never each other."""

from __future__ import annotations

import torch

from ..config import TrainConfig
from ..errors import InputError
from ..gaussians.init import knn_mean_distance, random_init, visual_hull
from ..gaussians.splats import Splats, create_splats
from ..progress import log
from ..scene.dataset import PreparedScene
from ..wavelet.haar import dwt2

VIEWS = "views.json"  # 4_repair: the pseudo views' cameras and weights
CKPT = "ckpt.pt"
PLY = "point_cloud.ply"


def initial_splats(scene: PreparedScene, cfg: TrainConfig, seed: int) -> Splats:
    """Visual hull of the masks when the scene has them, else random points in the object region."""
    gen = torch.Generator().manual_seed(seed)
    if scene.has_masks:
        try:
            pts, cols = visual_hull(scene.train, cfg.hull_resolution, 1.0, cfg.init_points, generator=gen)
        except InputError as exc:  # name the scene the user gave, whose masks and poses are at fault
            raise InputError(exc.message, scene.info.get("source")) from None
    else:
        log("coarse: no masks -> no visual hull, no mask loss, no random background (random init)")
        pts, cols = random_init(cfg.init_points, generator=gen)
    scales = knn_mean_distance(pts, 3).clamp(1e-4, 0.05)
    return create_splats(pts, cols, scales, cfg.sh_degree)


def background_for(scene: PreparedScene) -> torch.Tensor:
    """Renders and references on disk are composited on white for masked objects (the datasets' way)."""
    return torch.ones(3) if scene.has_masks else torch.zeros(3)


def subbands_hwc(img: torch.Tensor) -> dict[str, object]:
    """[H, W, 3] -> {"LL","LH","HL","HH": [h, w, 3] numpy} with one Haar level."""
    ll, [(lh, hl, hh)] = dwt2(img.permute(2, 0, 1)[None].double(), 1)
    return {n: b[0].permute(1, 2, 0).float().numpy() for n, b in (("LL", ll), ("LH", lh), ("HL", hl), ("HH", hh))}


def newest_model(ws) -> str:
    """The stage whose model a command shows by default: fine when it has run, else coarse."""
    return "fine" if ws.manifest("fine") is not None else "coarse"
