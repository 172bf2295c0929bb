"""LightGlue with its cross-attention fused (`learned_matching.fused_cross_attention`, what wgs
runs) against kornia's own forward: the same 4 generated photos (tests/photo_scene.py, 320x240,
masks, 45 degrees apart), their 6 pairs matched both ways in turn on one thread; the time of each
round, and per pair whether the matches are the same and how far the confidences differ. Then
ALIKED's extraction of the 4 photos channels-last (what wgs runs) against contiguous, in turn.

    python tools/experiments/xp_fused_attention.py [--rounds 2]
"""

import argparse
import itertools
import sys
import tempfile
import time
from functools import partial
from pathlib import Path

import numpy as np
import torch

# the repository root (tools/) and tests/ (the photo generator), run as a script from anywhere
sys.path[:0] = [str(Path(__file__).resolve().parents[2]), str(Path(__file__).resolve().parents[2] / "tests")]
from photo_scene import make_photos  # noqa: E402

from wgs.io.images import read_image  # noqa: E402
from wgs.scene import learned_matching as lm  # noqa: E402
from wgs.scene.sfm import find_photos, grown_masks  # noqa: E402


def use_fused(matcher: torch.nn.Module, fused: bool) -> None:
    for layer in matcher.transformers:
        if fused:
            layer.cross_attn.forward = partial(lm.fused_cross_attention, layer.cross_attn)
        elif "forward" in vars(layer.cross_attn):
            del layer.cross_attn.forward  # kornia's own


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--rounds", type=int, default=2)
    args = ap.parse_args()
    torch.set_num_threads(1)
    with tempfile.TemporaryDirectory() as tmp:
        make_photos(Path(tmp), n=4, azimuths=[0, 45, 90, 135])
        image_dir, names, mask_dir = find_photos(Path(tmp))
        masks = grown_masks(image_dir, names, mask_dir) if mask_dir is not None else {}
        images = [read_image(image_dir / n)[..., :3] for n in names]
        feats = [lm.extract(image, masks.get(n)) for n, image in zip(names, images, strict=True)]
    _, matcher = lm._models()
    pairs = list(itertools.combinations(range(len(feats)), 2))
    seconds: dict[str, list[float]] = {"fused": [], "kornia": []}
    out = {}
    for _ in range(args.rounds):
        for mode in seconds:
            use_fused(matcher, mode == "fused")
            t0 = time.perf_counter()
            out[mode] = [lm.match(feats[i], feats[j]) for i, j in pairs]
            seconds[mode].append(time.perf_counter() - t0)
    use_fused(matcher, True)
    print(f"keypoints {[len(f.keypoints) for f in feats]}; seconds for {len(pairs)} pairs: {seconds}")
    print("| pair | matches fused / kornia | same | confident fused / kornia | largest confidence difference |")
    print("| --- | ---: | --- | ---: | ---: |")
    for (i, j), (ma, sa), (mb, sb) in zip(pairs, out["fused"], out["kornia"], strict=True):
        same = ma.shape == mb.shape and bool((ma == mb).all())
        diff = f"{np.abs(sa - sb).max():.1e}" if same else ""
        print(f"| {i}+{j} | {len(ma)} / {len(mb)} | {same} | {(sa > 0.5).sum()} / {(sb > 0.5).sum()} | {diff} |")
    extractor, _ = lm._models()
    layouts = {"channels-last": torch.channels_last, "contiguous": torch.contiguous_format}
    extract_s: dict[str, list[float]] = {k: [] for k in layouts}
    found = {}
    for _ in range(args.rounds):
        for mode, layout in layouts.items():
            extractor.to(memory_format=layout)
            t0 = time.perf_counter()
            found[mode] = [lm.extract(image, masks.get(n)) for n, image in zip(names, images, strict=True)]
            extract_s[mode].append(time.perf_counter() - t0)
    extractor.to(memory_format=torch.channels_last)
    pairs_found = zip(found["channels-last"], found["contiguous"], strict=True)
    same = all(np.allclose(a.keypoints, b.keypoints, atol=1e-3) for a, b in pairs_found)
    print(f"seconds to extract {len(images)} photos: {extract_s}; the same keypoints: {same}")


if __name__ == "__main__":
    main()
