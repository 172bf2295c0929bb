"""`wgs all` on 4 photos without cameras against the same run with their true cameras, both scored
at the true test cameras: the posed model's world is aligned to the true one by the similarity
that takes its 4 training camera centres onto the true ones (Umeyama), and each true test camera
is moved into the model's world by it. The run with true cameras is scored the same way (its own
world is a normalised copy of the true one), so both numbers come from one scorer. Two more
columns score G_f with the test views given the run's own focal length (one camera took every
photo, and the model is drawn to the focal that structure-from-motion found), aligned by the
centres as above and by the cameras' rotations and centres (`pose_error.camera_similarity`). The
last two: the alignment refined by the photos, one similarity for every test camera (7 degrees of
freedom, `fit_similarity`, fitted on `--align-views` of them; in brackets the score on the others),
from the true focal and from the run's own aligned by the cameras. Every run is scored each way,
the one with true cameras too: the fit moves its cameras off the truth by what it gains on L1.

`--exif`: two more runs on the same 4 photos written as JPEGs whose EXIF gives their focal length
(35 mm equivalent in whole millimetres, `photo_scene.as_exif_jpegs`), as a phone's photos carry
it: with the defaults (EXIF's focal refined) and with `[prepare] hold_exif_focal = true`.

Scenes: 4 NeRF-Synthetic lego views along a chain about `--step` degrees apart (measuring only;
its 200 test views) and a generated object (tests/photo_scene.py) at the same spacing, with 12
views around it as test views. Runs go to `--out` (a cache outside the repository) and are kept:
a second call scores them again without training.

    python tools/experiments/xp_unposed_run.py [--lego ../shared/data/lego] [--step 45] [--out DIR] [--exif]
        [--only generated --shape 1]
"""

import argparse
import json
import os
import shutil
import subprocess
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

# the repository root (tools/) and tests/ (the photo generator), run as a script from anywhere
sys.path[:0] = [str(Path(__file__).resolve().parents[2]), str(Path(__file__).resolve().parents[2] / "tests")]
sys.path.insert(0, str(Path(__file__).resolve().parent))
from photo_scene import as_exif_jpegs, make_photos  # noqa: E402
from xp_sparse_pose import lego_chain  # noqa: E402

from wgs.gaussians.localise import axis_angle_quat, localise  # noqa: E402
from wgs.gaussians.project import quat_multiply, quat_to_rotmat  # noqa: E402
from wgs.gaussians.render import rasterize  # noqa: E402
from wgs.gaussians.splats import activate, load_checkpoint  # noqa: E402
from wgs.io import read_json  # noqa: E402
from wgs.io.images import downscale, read_image, split_rgba, write_png  # noqa: E402
from wgs.scene.convention import c2w_opengl_to_w2c_opencv  # noqa: E402
from wgs.scene.dataset import Frame, composite, load_prepared  # noqa: E402
from wgs.scene.pose_error import camera_similarity, centers, pose_errors, umeyama  # noqa: E402
from wgs.stages.eval.scoring import evaluate_model, spread, summarise  # noqa: E402
from wgs.workspace import Workspace  # noqa: E402

WGS = str(Path(sys.executable).with_name("wgs"))


def transforms_json(path: Path, frames: list[tuple[str, np.ndarray]], angle_x: float) -> None:
    """A NeRF-Synthetic transforms file: (file path without .png, w2c OpenCV) per frame."""
    flip = np.diag([1.0, -1.0, -1.0, 1.0])  # OpenCV <-> OpenGL camera axes
    rows = [{"file_path": p, "transform_matrix": (np.linalg.inv(w2c) @ flip).tolist()} for p, w2c in frames]
    path.write_text(json.dumps({"camera_angle_x": angle_x, "frames": rows}))


def lego_scene(lego: Path, step: float, out: Path) -> dict:
    """`out/unposed` (4 photos on white + masks) and `out/posed` (the same 4 with their cameras,
    and lego's test views); returns the true cameras {name: (K, w2c, rgba path)} of the tests."""
    truth = lego_chain(lego, step, out / "unposed")
    meta = json.loads((lego / "transforms_train.json").read_text())
    posed = out / "posed"
    (posed / "train").mkdir(parents=True, exist_ok=True)
    frames = []
    for name, w2c in truth.items():  # copies in the cache: wgs refuses paths outside the scene folder
        shutil.copyfile(lego / "train" / name, posed / "train" / name)
        frames.append((f"./train/{Path(name).stem}", w2c))
    transforms_json(posed / "transforms_train.json", frames, meta["camera_angle_x"])
    test = json.loads((lego / "transforms_test.json").read_text())
    (posed / "test").mkdir(exist_ok=True)
    for fr in test["frames"]:
        name = Path(fr["file_path"]).name + ".png"
        shutil.copyfile(lego / "test" / name, posed / "test" / name)
    (posed / "transforms_test.json").write_text(json.dumps(test))
    f = 400 / (2 * np.tan(test["camera_angle_x"] / 2))
    K = np.array([[f, 0, 200], [0, f, 200], [0, 0, 1.0]])
    tests = {
        Path(fr["file_path"]).name: (K, c2w_opengl_to_w2c_opencv(np.array(fr["transform_matrix"])), None)
        for fr in test["frames"]
    }
    for name in tests:
        tests[name] = (K, tests[name][1], lego / "test" / f"{name}.png")
    return {"truth": truth, "tests": tests}


def generated_scene(step: float, out: Path, shape: int | None = None) -> dict:
    """A generated object (`shape`: another one, `make_photos`' shape_seed): 4 photos `step` degrees
    apart, and 12 test views around it."""
    azimuths = [step * i for i in range(4)] + [15 + 30 * i for i in range(12)]
    every = out / "all"
    cams = make_photos(every, n=len(azimuths), azimuths=azimuths, shape_seed=shape)
    names = sorted(cams)
    (out / "posed" / "train").mkdir(parents=True, exist_ok=True)
    (out / "posed" / "test").mkdir(parents=True, exist_ok=True)
    truth, tests, frames = {}, {}, {"train": [], "test": []}
    for i, name in enumerate(names):
        K, w2c = cams[name]
        rgb, alpha = read_image(every / "images" / name)[..., :3], read_image(every / "masks" / name)[..., :1]
        rgba = np.concatenate([rgb, alpha], -1)
        split = "train" if i < 4 else "test"
        write_png(out / "posed" / split / name, rgba)
        frames[split].append((f"./{split}/{Path(name).stem}", w2c))
        if split == "train":
            write_png(out / "unposed" / "images" / name, read_image(every / "images" / name)[..., :3])
            write_png(out / "unposed" / "masks" / name, read_image(every / "masks" / name)[..., 0])
            truth[name] = w2c
        else:
            tests[Path(name).stem] = (K, w2c, out / "posed" / split / name)
    angle_x = 2 * np.arctan(K[0, 2] / K[0, 0])
    for split in ("train", "test"):
        transforms_json(out / "posed" / f"transforms_{split}.json", frames[split], angle_x)
    return {"truth": truth, "tests": tests}


def run_all(scene: Path, ws: Path, extra: list[str], config: Path | None = None) -> float:
    """`wgs all` (skipped when its report is there), with `config` where given; its wall time in
    seconds."""
    timing = ws / "xp_wall_s.txt"
    if timing.is_file():
        return float(timing.read_text())
    t0 = time.perf_counter()
    given = ["--config", str(config)] if config is not None else []
    subprocess.run([WGS, *given, "all", str(scene), "-w", str(ws), *extra], check=True)
    seconds = time.perf_counter() - t0
    timing.write_text(f"{seconds:.1f}")
    return seconds


def aligned_tests(
    ws: Path, truth: dict[str, np.ndarray], tests: dict, align: str = "centres", own_focal: bool = False
) -> tuple[list[Frame], dict]:
    """The true test cameras moved into the workspace's normalised world, at its working size,
    with their images; and the training poses' error against the truth.
    align: "centres" (Umeyama on the training cameras' centres) or "cameras" (their rotations,
    then their centres: `camera_similarity`). own_focal: the test views take the run's intrinsics
    (one camera took every photo; posed from 4 photos, its focal is a few per cent off, and the
    model is drawn to it), else the true ones."""
    ws_ = Workspace(ws)
    scene = load_prepared(ws_.output("prepare", "prepared"))
    # prepare names a view by its split ("train_photo_000.png"): match on the photo's own name
    own = {f.name: next(k for k in truth if Path(f.name).stem.endswith(Path(k).stem)) for f in scene.photos}
    est = {own[f.name]: f.viewmat.double().numpy() for f in scene.photos}
    names = sorted(est)
    true_w2c = np.stack([truth[n] for n in names])
    est_w2c = np.stack([est[n] for n in names])
    similarity = umeyama(centers(true_w2c), centers(est_w2c)) if align == "centres" else None
    s, R, t = similarity or camera_similarity(true_w2c, est_w2c)  # true world -> model world
    size = scene.photos[0].width
    run_K = scene.photos[0].K.double().numpy()
    frames = []
    for name, (K, w2c, path) in tests.items():
        rgb, mask = split_rgba(read_image(path))
        k = rgb.shape[1] // size
        rgb, mask = downscale(rgb, mask, k)
        Rc, tc = w2c[:3, :3], w2c[:3, 3]
        moved = np.eye(4)
        moved[:3, :3] = Rc @ R.T
        moved[:3, 3] = s * tc - Rc @ R.T @ t
        Kk = K.copy()
        Kk[:2] /= k
        if own_focal:
            Kk[0, 0], Kk[1, 1] = run_K[0, 0], run_K[1, 1]
        frames.append(
            Frame(
                torch.tensor(Kk, dtype=torch.float32),
                torch.tensor(moved, dtype=torch.float32),
                rgb.shape[1],
                rgb.shape[0],
                name=name,
                image=torch.from_numpy(np.ascontiguousarray(rgb)),
                mask=torch.from_numpy(np.ascontiguousarray(mask)),
            )
        )
    err = pose_errors(est_w2c, true_w2c)
    return frames, {
        "focal_ratio": float(run_K[0, 0] / (tests[next(iter(tests))][0][0, 0] / k)),
        "rotation_deg": float(np.median(err["rotation_deg"])),
        "centre": float(np.median(err["center"])),
        "norm": scene.norm,
    }


def fit_similarity(
    splats, frames: list[Frame], bg: torch.Tensor, steps: int, lr: float = 2e-3
) -> tuple[torch.Tensor, torch.Tensor]:
    """One similarity for all the test cameras (7 degrees of freedom, Adam on the photometric L1 of
    every frame at once) where the frozen model fits their photos best: the alignment of the two
    worlds refined by the photos, against `localise`'s 6 per camera. The world moves instead (x ->
    s R (x - c) + c + tau about the model's centroid c, the Gaussians' scales times s).
    Returns world [4, 4] = [R | t] and s: the moved world is s R x + t."""
    means, quats, scales, opac, sh = (t.detach().cpu() for t in activate(splats))
    c = means.mean(0)
    truths = [composite(f.pixels, f.mask, bg) for f in frames]
    omega, tau, log_s = (torch.zeros(n, requires_grad=True) for n in (3, 3, 1))
    opt = torch.optim.Adam([omega, tau, log_s], lr=lr)
    for _ in range(steps):
        R, s = quat_to_rotmat(axis_angle_quat(omega)[None])[0], log_s.exp()
        moved = s * (means - c) @ R.T + c + tau
        q = quat_multiply(axis_angle_quat(omega).expand_as(quats), quats)
        loss = sum(
            (rasterize(moved, q, scales * s, opac, sh, f.viewmat, f.K, f.width, f.height, bg)[0] - truth).abs().mean()
            for f, truth in zip(frames, truths, strict=True)
        )
        opt.zero_grad()
        loss.backward()
        opt.step()
    with torch.no_grad():
        R, s = quat_to_rotmat(axis_angle_quat(omega)[None])[0], log_s.exp()
        world = torch.eye(4)
        world[:3, :3], world[:3, 3] = R, c + tau - s * R @ c
    return world, s


def moved_cameras(frames: list[Frame], world: torch.Tensor, s: torch.Tensor) -> list[Frame]:
    """Each camera [Rc | tc] that sees the unmoved model as it saw the world moved by (world, s):
    [Rc R | (Rc t + tc) / s] (a view does not change when the whole scene is scaled)."""
    out = []
    for f in frames:
        m = f.viewmat @ world
        m[:3, 3] /= s
        out.append(replace(f, viewmat=m))
    return out


def score(
    ws: Path, frames: list[Frame], norm, stage: str, refine_steps: int = 0, align: tuple[int, int] = (0, 0)
) -> dict:
    """G_`stage`'s PSNR and IoU at `frames`: as given, each localised (`refine_steps`), or all moved by
    one similarity fitted on `align` = (steps, views spread among them)."""
    splats, _ = load_checkpoint(Workspace(ws).output(stage, "model"), norm, "cpu")
    bg = torch.ones(3)
    if refine_steps:
        frames = [localise(splats, f, bg, refine_steps)[0] for f in frames]
    fitted_on: set[str] = set()
    if align[0]:
        fitted_on = {f.name for f in spread(frames, align[1])}
        fit = fit_similarity(splats, [f for f in frames if f.name in fitted_on], bg, align[0])
        frames = moved_cameras(frames, *fit)
    per = evaluate_model(splats, frames, torch.device("cpu"), bg, None, desc=f"score {stage}")
    s = summarise(per)
    out = {"psnr": s["psnr"], "iou": s["silhouette_iou"]}
    if fitted_on:  # the views the similarity was not fitted on alone
        rest = {m: {k: v for k, v in vals.items() if k not in fitted_on} for m, vals in per.items()}
        out["psnr_unfitted"] = summarise(rest)["psnr"]
    return out


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--lego", type=Path, default=Path("../shared/data/lego"))
    ap.add_argument("--step", type=float, default=45)
    cache = Path(os.environ.get("WGS_CACHE", "~/.cache/wgs")).expanduser()
    ap.add_argument("--out", type=Path, default=cache / "xp_unposed")
    ap.add_argument("--only", choices=("lego", "generated"), default=None)
    ap.add_argument("--refine-views", type=int, default=40, help="test views scored after test-pose refinement")
    ap.add_argument("--refine-steps", type=int, default=60)
    ap.add_argument("--shape", type=int, default=None, help="the generated object's shape seed (another object)")
    ap.add_argument("--align-steps", type=int, default=100, help="Adam steps of the similarity fitted on the photos")
    ap.add_argument("--align-views", type=int, default=6, help="test views the similarity is fitted on")
    ap.add_argument("--exif", action="store_true", help="also the 4 photos as JPEGs whose EXIF gives their focal")
    args = ap.parse_args()
    scenes = []
    if args.only in (None, "generated"):
        label = "generated" if args.shape is None else f"generated{args.shape}"
        scenes.append((label, lambda step, out: generated_scene(step, out, args.shape), ["--downscale", "1"], []))
    if args.only in (None, "lego") and (args.lego / "transforms_train.json").is_file():
        scenes.append(("lego", lambda step, out: lego_scene(args.lego, step, out), ["--downscale", "2"], []))
    rows = []
    for label, make, extra, _ in scenes:
        out = args.out / f"{label}_{args.step:g}"
        data = make(args.step, out)
        # (workspace, photos, config, cameras)
        kinds = [("posed", "posed", None, "true"), ("unposed", "unposed", None, "posed by wgs")]
        if args.exif:
            if not (out / "unposed_exif").is_dir():
                shutil.copytree(out / "unposed", out / "unposed_exif")
                as_exif_jpegs(out / "unposed_exif", float(next(iter(data["tests"].values()))[0][0, 0]))
            held = out / "hold_exif_focal.toml"
            held.write_text("[prepare]\nhold_exif_focal = true\n")
            kinds += [
                ("unposed_exif", "unposed_exif", None, "posed by wgs, EXIF's focal refined"),
                ("unposed_exif_held", "unposed_exif", held, "posed by wgs, EXIF's focal held"),
            ]
        fit = (args.align_steps, args.align_views)
        for kind, photos, config, cameras in kinds:
            ws = out / f"ws_{kind}"
            wall = run_all(out / photos, ws, extra, config)
            frames, pose = aligned_tests(ws, data["truth"], data["tests"])
            rows.append(
                {
                    "scene": f"{label}, {args.step:g} deg",
                    "cameras": cameras,
                    "wall_s": wall,
                    "rotation_deg": pose["rotation_deg"],
                    "centre": pose["centre"],
                    "coarse": score(ws, frames, pose["norm"], "coarse"),
                    "fine": score(ws, frames, pose["norm"], "fine"),
                    "fine_refined": score(
                        ws, spread(frames, args.refine_views), pose["norm"], "fine", args.refine_steps
                    ),
                    "own_eval": read_json(Workspace(ws).output("eval", "results"))["psnr"],
                    "focal_ratio": pose["focal_ratio"],
                    "own_focal": score(
                        ws, aligned_tests(ws, data["truth"], data["tests"], own_focal=True)[0], pose["norm"], "fine"
                    ),
                    "cameras_own_focal": score(
                        ws, aligned_tests(ws, data["truth"], data["tests"], "cameras", True)[0], pose["norm"], "fine"
                    ),
                    "fitted": score(ws, frames, pose["norm"], "fine", align=fit),
                    "fitted_own_focal": score(
                        ws,
                        aligned_tests(ws, data["truth"], data["tests"], "cameras", True)[0],
                        pose["norm"],
                        "fine",
                        align=fit,
                    ),
                }
            )
    print(
        "| scene | cameras | pose error (deg / % extent) | G_c PSNR | G_f PSNR | G_f IoU | G_f PSNR, test poses "
        "refined | wgs all (s) | its own eval (dB) | focal / true | G_f PSNR / IoU, the run's focal | "
        "the same, aligned on the cameras' rotations | G_f PSNR / IoU, one similarity fitted on the photos: "
        "true focal, the run's (the views it was not fitted on) |"
    )
    print("| --- | --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |")
    for r in rows:
        print(
            f"| {r['scene']} | {r['cameras']} | {r['rotation_deg']:.2f} / {100 * r['centre']:.1f} | "
            f"{r['coarse']['psnr']:.2f} | {r['fine']['psnr']:.2f} | {r['fine']['iou']:.3f} | "
            f"{r['fine_refined']['psnr']:.2f} | {r['wall_s']:.0f} | {r['own_eval']:.2f} | {r['focal_ratio']:.3f} | "
            f"{r['own_focal']['psnr']:.2f} / {r['own_focal']['iou']:.3f} | "
            f"{r['cameras_own_focal']['psnr']:.2f} / {r['cameras_own_focal']['iou']:.3f} | "
            f"{r['fitted']['psnr']:.2f} ({r['fitted']['psnr_unfitted']:.2f}) / {r['fitted']['iou']:.3f}, "
            f"{r['fitted_own_focal']['psnr']:.2f} ({r['fitted_own_focal']['psnr_unfitted']:.2f}) / "
            f"{r['fitted_own_focal']['iou']:.3f} |"
        )


if __name__ == "__main__":
    main()
