"""Leave-one-out pairs at the object's own novel poses: 3-view models' renders -> the 4-view
ensemble's mean render, D fine-tuned on them (+ the ORM pairs); references scored at 40 test poses.
usage: python xp_loo.py WS OUT [steps] [loo|loo+orm] [poses] [hull4]"""

import json
import shutil
import sys
import time
from pathlib import Path

import torch
from xp_lib import score_refs, train_subset

from wgs.config import resolve
from wgs.gaussians.splats import load_checkpoint
from wgs.gaussians.trainer import render_frame
from wgs.models.data import load_pairs, to_model
from wgs.models.repair import load_repairer
from wgs.models.storage import save_model
from wgs.scene.dataset import load_prepared
from wgs.scene.orbit import sphere_views
from wgs.stages.repair.settings import RepairConfig
from wgs.stages.shared import background_for, coarse_members
from wgs.threads import map_in_processes
from wgs.training.per_object import finetune_prior_d
from wgs.wavelet.haar import dwt2
from wgs.workspace import Workspace

if __name__ == "__main__":
    ws, out = Workspace(Path(sys.argv[1])), Path(sys.argv[2])
    steps = int(sys.argv[3]) if len(sys.argv) > 3 else 300
    mix = sys.argv[4] if len(sys.argv) > 4 else "loo+orm"
    npose = int(sys.argv[5]) if len(sys.argv) > 5 else 64
    hull_all = len(sys.argv) > 6 and sys.argv[6] == "hull4"
    out.mkdir(parents=True, exist_ok=True)
    dev = torch.device("cpu")
    sdir = ws.stage_dir("prepare")
    scene = load_prepared(sdir, load_test_images=True)
    n = len(scene.train)
    jobs = [
        (str(sdir), [i for i in range(n) if i != j], 100 + j, str(out / f"loo_{j}.pt"), None, hull_all)
        for j in range(n)
        if not (out / f"loo_{j}.pt").is_file()
    ]
    t0 = time.perf_counter()
    for _ in map_in_processes(train_subset, jobs, 2):
        pass
    print(f"LOO models: {time.perf_counter() - t0:.0f} s", flush=True)
    loo = [load_checkpoint(out / f"loo_{j}.pt", scene.norm)[0] for j in range(n)]
    members = coarse_members(ws, scene, dev)
    bg = background_for(scene)
    rcfg = RepairConfig()
    pairs_path = out / f"pairs_{npose}.pt"
    if not pairs_path.is_file():
        clean, bad = [], []
        for f, _ in sphere_views(scene.train, npose, rcfg.band_below, rcfg.band_above):
            with torch.no_grad():
                target = torch.stack([render_frame(m, f, dev, bg)[0] for m in members]).mean(0)
                ll_t = dwt2(target.permute(2, 0, 1)[None].double(), 1)[0].float()
                for m in loo:
                    r = render_frame(m, f, dev, bg)[0]
                    clean.append(ll_t[0])
                    bad.append(dwt2(r.permute(2, 0, 1)[None].double(), 1)[0].float()[0])
        torch.save(
            {"clean": to_model(torch.stack(clean), "wavelet"), "bad": to_model(torch.stack(bad), "wavelet")}, pairs_path
        )
    p = torch.load(pairs_path)
    lc, lb = p["clean"], p["bad"]
    oc, ob, _ = load_pairs(ws.output("mask_data", "index"), "wavelet", 1)
    print(
        f"pairs: LOO {lc.shape[0]}, ORM {oc.shape[0]}; LOO identity MSE {float((lc - lb).pow(2).mean()):.5f}",
        flush=True,
    )
    gen = torch.Generator().manual_seed(0)
    perm = torch.randperm(lc.shape[0], generator=gen)
    hold = perm[: lc.shape[0] // 8]
    tr = perm[lc.shape[0] // 8 :]
    if mix == "loo":
        c, b = lc[tr], lb[tr]
    else:
        c, b = torch.cat([lc[tr], oc]), torch.cat([lb[tr], ob])
    fcfg = resolve("finetune", cli={"prior_steps": steps})
    start = ws.stage_dir("finetune")
    t0 = time.perf_counter()
    model, meta, curve = finetune_prior_d(fcfg, start, c, b, lc[hold], lb[hold], dev, gen)
    print(
        f"finetune {time.perf_counter() - t0:.0f} s; held-out LOO MSE {curve['bar']:.5f} -> "
        f"{curve['best']:.5f} (stopped {curve['stopped_at']})",
        flush=True,
    )
    folder = out / f"ft_{mix}_{steps}_{npose}"
    shutil.rmtree(folder, ignore_errors=True)
    save_model(folder / "D", model, meta.to_config())
    if (start / "U").is_dir():
        shutil.copytree(start / "U", folder / "U")
    test = scene.test[::5]
    base = score_refs(members, test, bg, load_repairer(start, rcfg, dev, 0))
    new = score_refs(members, test, bg, load_repairer(folder, rcfg, dev, 0))
    res = {"steps": steps, "mix": mix, "npose": npose, "refs_base": base, "refs_new": new, "curve_val": curve["val"]}
    print(json.dumps(res), flush=True)
    with open(out / "results.jsonl", "a") as fh:
        fh.write(json.dumps(res) + "\n")
