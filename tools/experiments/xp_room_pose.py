"""4 photos of a generated object in a room (repeating textures), posed by wgs, against the truth;
and what checks such poses: the hull of the photos' own masks, or nothing (automatic masks).

Per object (`examples/make_scene.py OUT --room --kind K --seed S --size 400 --train 9 --test 1`,
training photos 0-3):
- the neighbours' relative rotations and the median rotation error after a similarity alignment
  (`pose_errors`), posed by `sfm.pose_photos` without masks and with the true masks;
- `wgs prepare` on the photos with the true masks: the pose check's verdict (its error, or its
  "cameras:" line);
- `wgs prepare --masks auto` on the photos alone (posed by wgs) and on the same 4 photos with the
  true cameras: the automatic masks' vote (`cut_by_agreement`, mean share of the network's object
  area it cut);
- with `--pilots`, on those two workspaces: the coarse stage's held-out pilots as a pose check
  (`pilot_check`): per photo, a pilot trained on the other three (`train_pilot`, to its cap, no
  early end), its best PSNR at the photo it held out (and where, and at its end), against that
  photo predicted by the background alone and by the most alike other photo.

    python tools/experiments/xp_room_pose.py [--objects box:5 mug:9 cabinet:7 vase:43 blobs:3] [--pilots]
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
sys.path[:0] = [str(ROOT), str(ROOT / "tests"), str(Path(__file__).resolve().parent)]
from xp_close_up_pose import posed  # noqa: E402

from wgs.scene.convention import c2w_opengl_to_w2c_opencv  # noqa: E402

PHOTOS = range(4)


def angle(R: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1, 1))))


def photos(src: Path, out: Path, masks: bool) -> dict[str, np.ndarray]:
    """Photos 0-3 of `src` as `out/images` (and `out/masks`); {name: true w2c}."""
    meta = json.loads((src / "transforms_train.json").read_text())
    truth = {}
    for i in PHOTOS:
        path = meta["frames"][i]["file_path"]
        name = f"photo_{i}.png"
        (out / "images").mkdir(parents=True, exist_ok=True)
        shutil.copy(src / f"{path}.png", out / "images" / name)
        if masks:
            (out / "masks").mkdir(exist_ok=True)
            shutil.copy(src / "true_masks" / f"{Path(path).name}_train.png", out / "masks" / name)
        truth[name] = c2w_opengl_to_w2c_opencv(np.array(meta["frames"][i]["transform_matrix"]))
    return truth


def prepare(folder: Path, ws: Path, *extra: str) -> str:
    out = subprocess.run(
        [sys.executable, "-m", "wgs", "-w", str(ws), "prepare", str(folder), *extra], capture_output=True, text=True
    )
    text = " ".join((out.stdout + out.stderr).split())
    if out.returncode:
        return text[text.index("error:") :][:400] if "error:" in text else f"rc {out.returncode}"
    masks = json.loads((ws / "scene" / "scene.json").read_text())["masks"]
    line = text[text.index("cameras:") :][:200] if "cameras:" in text else ""
    cut = masks.get("cut_by_agreement", {}).get("mean")
    return f"{line}" if cut is None else f"vote cut {100 * cut:.1f} % ({masks['source']})"


def pilot_check(ws: Path) -> str:
    """Per training photo: the held-out pilot's best PSNR @ its iteration -> at its end, then the
    photo predicted by the background alone and by the most alike other photo (dB)."""
    import torch

    from wgs.metrics import psnr
    from wgs.scene.dataset import composite, halved, load_prepared
    from wgs.stages.coarse.run import train_pilot
    from wgs.stages.coarse.settings import CoarseConfig
    from wgs.stages.shared import background_for
    from wgs.workspace import Workspace

    space = Workspace(ws)
    scene = load_prepared(space.output("prepare", "prepared"))
    bg = background_for(scene)
    views = {f.name: halved(f) for f in scene.colour_views}
    refs = {n: composite(f.pixels, f.mask, bg) for n, f in views.items()}
    said = []
    for name, ref in refs.items():
        curve = train_pilot(space, CoarseConfig(), torch.device("cpu"), 0, name, end_when_past=False)
        at, best = max(curve, key=lambda c: c[1])
        blank = psnr(bg.reshape(1, 1, -1).expand_as(ref), ref)
        alike = max(psnr(r, ref) for n, r in refs.items() if n != name and r.shape == ref.shape)
        said.append(f"{best:.2f} @{at} -> {curve[-1][1]:.2f} (blank {blank:.2f}, alike {alike:.2f})")
    return "; ".join(said)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--objects", nargs="+", default=["box:5", "mug:9", "cabinet:7", "vase:43", "blobs:3"])
    ap.add_argument("--pilots", action="store_true", help="the held-out pilots as a pose check (pilot_check)")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        t = Path(tmp)
        for spec in args.objects:
            kind, seed = spec.split(":")
            src = t / f"{kind}_{seed}"
            subprocess.run(
                [sys.executable, str(ROOT / "examples/make_scene.py"), str(src), "--room", "--kind", kind]
                + ["--seed", seed, "--size", "400", "--train", "9", "--test", "1"],
                check=True,
                capture_output=True,
            )
            truth = photos(src, t / f"{spec}_bare", masks=False)
            photos(src, t / f"{spec}_masked", masks=True)
            names = sorted(truth)
            turns = [angle(truth[b][:3, :3] @ truth[a][:3, :3].T) for a, b in zip(names, names[1:], strict=False)]
            # the same 4 photos with their true cameras, NeRF-Synthetic style
            known = t / f"{spec}_known"
            (known / "train").mkdir(parents=True)
            meta = json.loads((src / "transforms_train.json").read_text())
            for i in PHOTOS:
                shutil.copy(src / f"{meta['frames'][i]['file_path']}.png", known / "train")
            (known / "transforms_train.json").write_text(json.dumps({**meta, "frames": meta["frames"][:4]}))
            print(f"{kind} (seed {seed}), neighbours turned {', '.join(f'{x:.0f}' for x in turns)} deg:")
            print(f"  posed without masks: {posed(t / f'{spec}_bare', truth, t / f'{spec}_m1')}")
            print(f"  posed with the true masks: {posed(t / f'{spec}_masked', truth, t / f'{spec}_m2')}")
            print(f"  prepare, true masks: {prepare(t / f'{spec}_masked', t / f'{spec}_ws1')}")
            bare = prepare(t / f"{spec}_bare", t / f"{spec}_ws2", "--masks", "auto")
            print(f"  prepare, no masks, posed by wgs: {bare}")
            print(
                f"  prepare, no masks, true cameras: {prepare(known, t / f'{spec}_ws3', '--masks', 'auto')}", flush=True
            )
            if args.pilots:
                for what, ws in (("posed by wgs", t / f"{spec}_ws2"), ("true cameras", t / f"{spec}_ws3")):
                    if (ws / "scene" / "scene.json").is_file():
                        print(f"  pilots, no masks, {what}: {pilot_check(ws)}", flush=True)


if __name__ == "__main__":
    main()
