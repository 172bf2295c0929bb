"""What a photo should say outside its frame where the object runs out of it (`shape.hull.OFF_FRAME`),
on generated close-up scenes (`examples/make_scene.py --close-up`: the object runs out of every
training photo, the test views stand back and see all of it).

Per scene and rule: the strict and the tolerant hull's volume against the hull of 24 views from
all around that see the whole object, the strict hull's silhouette at the test views, and with
`--train` G_c's test PSNR (one coarse model per rule, the fast preset's coarse stage). No mirror
views: whether a mirror plane is taken depends on the hull too, and would decide G_c alone.

    python tools/experiments/xp_off_frame.py [--seeds 0,1,2,3] [--arc 180] [--cache ~/.cache/wgs-xp/off_frame] [--train]

--arc: the training photos' spread of azimuths in degrees (make_scene's CLOSE_UP_ARC by default).
"""

import argparse
import json
import math
import statistics
import subprocess
import sys
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "examples"))
import make_scene  # noqa: E402

import wgs.shape.hull as hull  # noqa: E402
from wgs.scene.convention import c2w_opengl_to_w2c_opencv, focal_from_fov  # noqa: E402
from wgs.scene.dataset import Frame, load_prepared  # noqa: E402
from wgs.shape.scores import mean_scores, silhouette_scores  # noqa: E402

RULES = {
    "object": ("object", None),
    "background": ("background", None),
    "abstain, 2 views": ("abstain", 2),
    "abstain": ("abstain", 3),
}


def set_rule(name: str) -> None:
    """Make `name` the rule every hull takes in this process."""
    rule, min_views = RULES[name]
    hull.OFF_FRAME_RULE = rule
    hull._hulls.clear()  # the process keeps hulls by their inputs, not by the rule's settings
    if min_views is not None:
        hull.MIN_HOLDING_VIEWS = min_views


def around(scene, seed: int, n: int = 24, size: int = 128) -> list[Frame]:
    """Masks of the scene's object from n cameras spread over the sphere, standing back, in the
    prepared scene's normalised world."""
    parts = make_scene.make_object(np.random.default_rng(seed))
    f = focal_from_fov(make_scene.FOV_X, size)
    K = torch.tensor([[f, 0, size / 2], [0, f, size / 2], [0, 0, 1]], dtype=torch.float32)
    out = []
    for i in range(n):  # a Fibonacci sphere
        z = 1 - 2 * (i + 0.5) / n
        a = i * math.pi * (3 - math.sqrt(5))
        eye = make_scene.STAND_BACK_DISTANCE * np.array(
            [math.sqrt(1 - z * z) * math.cos(a), math.sqrt(1 - z * z) * math.sin(a), z]
        )
        c2w = make_scene.look_at_c2w(eye)
        mask = make_scene.render(parts, c2w, size)[..., 3] > 0.5
        assert not (mask[0].any() or mask[-1].any() or mask[:, 0].any() or mask[:, -1].any())
        w2c = scene.norm.w2c_to_normalised(c2w_opengl_to_w2c_opencv(c2w))
        out.append(
            Frame(
                K,
                torch.tensor(w2c, dtype=torch.float32),
                size,
                size,
                name=f"a{i}",
                mask=torch.from_numpy(mask.astype(np.float32)),
            )
        )
    return out


def volume(grid) -> float:
    return float(grid.occ.sum()) * float(grid.cell.prod())


def coarse_psnr(ws: Path, scene_dir: Path, rule: str) -> float:
    """G_c's mean test PSNR with the coarse stage's hull init under `rule` (in a fresh process)."""
    code = (
        f"import sys; sys.argv = ['wgs']; sys.path.insert(0, {str(Path(__file__).parent)!r}); "
        f"import xp_off_frame as x; x.set_rule({rule!r}); from wgs.cli import main; "
        f"main(['-q', '-w', {str(ws)!r}, 'prepare', {str(scene_dir)!r}, '--mirror', 'none']); "
        f"main(['-q', '-w', {str(ws)!r}, 'coarse', '--preset', 'fast', '--ensemble', '1'])"
    )
    subprocess.run([sys.executable, "-c", code], check=True)
    from wgs.gaussians.splats import load_checkpoint
    from wgs.gaussians.trainer import render_frame
    from wgs.metrics import psnr
    from wgs.scene.dataset import composite
    from wgs.stages.shared import background_for
    from wgs.workspace import Workspace

    w = Workspace(ws)
    scene = load_prepared(w.output("prepare", "prepared"), load_test_images=True)
    bg = background_for(scene)
    splats, _ = load_checkpoint(w.output("coarse", "model"), scene.norm, torch.device("cpu"))
    vals = [
        psnr(render_frame(splats, f, torch.device("cpu"), bg)[0].clamp(0, 1), composite(f.image, f.mask, bg))
        for f in scene.test
    ]
    return float(statistics.fmean(float(v) for v in vals))


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--seeds", default="0,1,2,3")
    ap.add_argument("--cache", type=Path, default=Path.home() / ".cache/wgs-xp/off_frame")
    ap.add_argument("--train", action="store_true", help="also G_c's test PSNR per rule")
    ap.add_argument("--arc", type=float, default=math.degrees(make_scene.CLOSE_UP_ARC))
    a = ap.parse_args()
    make_scene.CLOSE_UP_ARC = math.radians(a.arc)
    rows = []
    for seed in (int(s) for s in a.seeds.split(",")):
        scene_dir = a.cache / f"closeup_{a.arc:g}_{seed}"
        if not (scene_dir / "transforms_test.json").is_file():
            make_scene.make_scene(scene_dir, seed, 128, 4, 8, close_up=True)
        ws = a.cache / f"wsnm_{a.arc:g}_{seed}"
        if not (ws / "scene").is_dir():
            subprocess.run(
                [sys.executable, "-m", "wgs", "-q", "-w", str(ws), "prepare", str(scene_dir), "--mirror", "none"],
                check=True,
            )
        scene = load_prepared(ws / "scene", load_test_images=True)
        photos = scene.photos
        reference = volume(hull.visual_hull_grid(around(scene, seed), 96, tolerate=0))
        for name in RULES:
            set_rule(name)
            strict = hull.visual_hull_grid(photos, 96, tolerate=0)
            tolerant = hull.visual_hull_grid(photos, 96)
            test = mean_scores(
                {f.name: silhouette_scores(hull.silhouette(strict, f)[0], f.mask > 0.5) for f in scene.test}
            )
            row = {
                "seed": seed,
                "rule": name,
                "strict_volume_x": volume(strict) / reference,
                "tolerant_volume_x": volume(tolerant) / reference,
                "strict_test_iou": test["iou"],
                "strict_test_missed": test["missed"],
            }
            if a.train:
                tag = name.replace(" ", "_").replace(",", "")
                row["gc_psnr"] = coarse_psnr(a.cache / f"wsnm_{a.arc:g}_{seed}_{tag}", scene_dir, name)
            rows.append(row)
            print(json.dumps({k: round(v, 4) if isinstance(v, float) else v for k, v in row.items()}), flush=True)
        set_rule("abstain")
    print("\nmeans over seeds")
    for name in RULES:
        mine = [r for r in rows if r["rule"] == name]
        keys = [k for k in mine[0] if k not in ("seed", "rule")]
        print(f"{name:>22}: " + ", ".join(f"{k} {statistics.fmean(r[k] for r in mine):.3f}" for k in keys))


if __name__ == "__main__":
    main()
