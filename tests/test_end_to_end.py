"""`wgs all` end to end on a tiny scene: the workspace contract, skip logic, leave-outs."""

import json
import math
import shutil

import numpy as np
import pytest
from click.testing import CliRunner
from conftest import make_scene

from wgs.cli import cli
from wgs.workspace import Workspace

CONTRACT = [
    "scene/scene.json",
    "scene/sparse/cameras.txt",
    "scene/sparse/images.txt",
    "scene/split_train.txt",
    "1_coarse/ckpt.pt",
    "1_coarse/point_cloud.ply",
    "1_coarse/train_psnr.json",
    "2_mask_data/index.json",
    "3_finetune/D/model.safetensors",
    "3_finetune/D/config.json",
    "3_finetune/curves.json",
    "3_finetune/curves.png",
    "4_repair/views.json",
    "4_repair/contact_sheet.png",
    "5_fine/ckpt.pt",
    "5_fine/point_cloud.ply",
    "6_eval/results.json",
    "6_eval/per_view.json",
    "6_eval/per_view_coarse.json",
    "6_eval/report.md",
    "6_eval/error_vs_time.png",
    "6_eval/report.html",
    "6_eval/turntable.gif",
]
STAGES = ["prepare", "coarse", "mask_data", "finetune", "repair", "fine", "eval"]


def run_all(cfg, ws, scene, *extra):
    res = CliRunner().invoke(
        cli, ["-q", "--config", str(cfg), "-w", str(ws), "all", str(scene), *extra], catch_exceptions=False
    )
    assert res.exit_code == 0, res.output
    return res


@pytest.fixture(scope="module")
def tiny(finished_workspace, tmp_path_factory):
    """The session's finished tiny workspace, copied: these tests render and rerun in it."""
    base, output = finished_workspace
    ws = tmp_path_factory.mktemp("e2e") / "ws"
    shutil.copytree(base / "ws", ws)
    return base / "scene", base / "wgs.toml", Workspace(ws), output


def finished(ws: Workspace) -> dict[str, str]:
    return {
        s: (ws.manifest(s) or {}).get("finished", "") + str((ws.manifest(s) or {}).get("wall_time_s")) for s in STAGES
    }


def test_workspace_contract_and_results(tiny):
    _, _, ws, output = tiny
    for rel in CONTRACT:
        assert (ws.root / rel).is_file(), rel
    res = json.loads((ws.root / "6_eval/results.json").read_text())
    for k in ("psnr", "psnr_std", "ssim", "ssim_std"):
        assert math.isfinite(res[k]) and math.isfinite(res["coarse"][k])
    assert res["num_views"] == 5 and res["num_gaussians"] > 0
    assert res["method"] == "wgs" and res["seed"] == 0 and res["version"] and res["scene"].endswith("scene")
    assert res["results"]["psnr"] == res["psnr"] and res["results"]["ssim_std"] == res["ssim_std"]  # ns-eval layout
    assert res["lpips"] is None and "not found" in res["lpips_unavailable"]
    per = json.loads((ws.root / "6_eval/per_view.json").read_text())
    assert len(per["psnr"]) == 5
    assert set(res["stage_times_s"]) == {"prepare", "coarse", "mask_data", "finetune", "repair", "fine"}
    assert "PSNR" in output and "report" in output
    report = (ws.root / "6_eval/report.md").read_text()
    page = (ws.root / "6_eval/report.html").read_text()
    # self-contained: plot, 2 worst + 2 best sheets (5 views), 3 worst outlines and the contact sheet embedded
    assert page.count("src='data:image/png;base64,") == 1 + 4 + 3 + 1 and "src='http" not in page
    assert len(list((ws.root / "6_eval/sheets").glob("*.png"))) == 4
    worst = min(per["psnr"], key=per["psnr"].get)
    assert page.index(worst) < page.index("Per view") and "Repair gain" in page
    assert page.count("src='data:image/gif;base64,") == 1  # the turntable
    for stage in ("1_coarse", "5_fine"):  # quality against training time on probe views
        curve = json.loads((ws.root / stage / "curve.json").read_text())
        its = [p["iteration"] for p in curve["points"]]
        assert its[0] == 0 and its == sorted(its) and len(its) >= 2 and len(curve["views"]) == 4
        assert all(math.isfinite(p["psnr"]) for p in curve["points"])
    assert "| coarse |" in report and "| fine |" in report
    # silhouettes: per view and as means for G_c and G_f, the hull's and the leave-one-out estimate
    assert set(per["silhouette_iou"]) == set(per["psnr"]) and len(list((ws.root / "6_eval/outlines").glob("*"))) == 5
    for q in (res, res["coarse"]):
        assert 0 < q["silhouette_iou"] <= 1 and q["silhouette_excess"] >= 0 and q["silhouette_missed"] >= 0
    shape = json.loads((ws.root / "6_eval/per_view_shape.json").read_text())
    assert len(shape["leave_one_out"]) == 4 and len(shape["hull_test"]) == 5  # 4 training views, 5 test views
    assert 0 < res["shape"]["leave_one_out"]["iou"] <= 1 and 0 < res["shape"]["hull_test"]["iou"] <= 1
    assert "leave-one-out" in report and "silhouette IoU" in page and "Silhouettes, worst first" in page
    gain = json.loads((ws.root / "6_eval/per_view_repair.json").read_text())
    assert set(gain["render"]) == set(gain["repaired"]) == set(per["psnr"])  # 5 views, fewer than 50
    mean_gain = sum(gain["repaired"][k] - gain["render"][k] for k in gain["render"]) / 5
    assert math.isclose(res["repair_gain"]["gain_db"], mean_gain) and res["repair_gain"]["num_views"] == 5
    views = json.loads((ws.root / "4_repair/views.json").read_text())
    assert len(views["views"]) == 16  # TINY's [repair] num_views over the sphere
    assert views["used_u"] is ws.manifest("finetune")["u_used"]  # U only where it beat no HF repair
    assert all(0 < v["weight"] <= 1 for v in views["views"])


def test_render_defaults_to_the_newest_model(tiny):
    _, _, ws, _ = tiny
    res = CliRunner().invoke(cli, ["-q", "-w", str(ws.root), "render", "--views", "test"], catch_exceptions=False)
    assert res.exit_code == 0, res.output
    assert len(list((ws.root / "renders" / "fine_test").glob("*.png"))) == 5
    assert not (ws.root / "renders" / "coarse_test").exists()
    res = CliRunner().invoke(
        cli, ["-q", "-w", str(ws.root), "render", "--views", "path", "--frames", "3", "--video"], catch_exceptions=False
    )
    assert res.exit_code == 0, res.output
    from PIL import Image

    with Image.open(ws.root / "renders" / "fine_path.gif") as gif:
        assert gif.n_frames == 3 and gif.size == (64, 64)


def test_baseline_plain_3dgs_for_the_same_time(tiny, tmp_path):
    """`wgs all --baseline` (what `make demo` runs) on a finished workspace: the estimate covers the
    baseline and eval, which reads it; the baseline runs, then eval again, which scores it."""
    scene, cfg, ws0, _ = tiny
    ws = tmp_path / "ws"
    shutil.copytree(ws0.root, ws)
    res = CliRunner().invoke(
        cli, ["--config", str(cfg), "-w", str(ws), "all", str(scene), "--baseline"], catch_exceptions=False
    )
    assert res.exit_code == 0, res.output
    assert "estimate: about" in res.output and "baseline " in res.output
    assert set(Workspace(ws).run_record()["estimate"]) == {"baseline", "eval"}
    assert Workspace(ws).manifest("eval")["upstream"]["baseline"] == Workspace(ws).manifest("baseline")["fingerprint"]
    out = json.loads((ws / "6_eval/results.json").read_text())
    b = out["baseline_3dgs"]
    assert math.isfinite(b["psnr"]) and b["budget_s"] > 0 and b["iterations"] > 0
    assert b["train_seconds"] <= b["budget_s"] + 5.0
    curve = json.loads(Workspace(ws).output("baseline", "curve").read_text())
    assert curve["points"][0]["iteration"] == 0 and len(curve["points"]) >= 2
    assert "Plain 3DGS for the same training time" in (ws / "6_eval/report.html").read_text()
    # the plot's curves, also in results.json: coarse, fine and the baseline on one time axis
    assert set(out["curves"]) == {"coarse", "fine", "plain 3DGS"}
    assert abs(out["curves"]["plain 3DGS"][0][0] - out["curves"]["coarse"][0][0]) < 0.5  # both start with coarse


def test_repair_gain_at_test_poses_spread_over_them(tiny, tmp_path):
    from wgs.stages.eval.scoring import spread

    assert spread(list(range(200)), 50) == list(range(0, 200, 4))
    assert spread(list(range(7)), 3) == [0, 2, 4]
    assert spread(list(range(5)), 0) == spread(list(range(5)), 50) == list(range(5))
    _, cfg, ws0, _ = tiny
    ws = tmp_path / "ws"
    shutil.copytree(ws0.root, ws)
    res = CliRunner().invoke(
        cli,
        ["-q", "--config", str(cfg), "-w", str(ws), "eval", "--force", "--repair-gain-views", "2"],
        catch_exceptions=False,
    )
    assert res.exit_code == 0, res.output
    out = json.loads((ws / "6_eval/results.json").read_text())
    names = list(json.loads((ws / "6_eval/per_view.json").read_text())["psnr"])  # in the test views' order
    gain = json.loads((ws / "6_eval/per_view_repair.json").read_text())
    assert out["repair_gain"]["num_views"] == 2 and out["num_views"] == 5
    assert sorted(gain["render"]) == sorted(names[i] for i in (0, 2))


def test_second_run_recomputes_nothing_and_fine_option_reruns_fine_and_eval(tiny, tmp_path):
    scene, cfg, ws0, _ = tiny
    ws = Workspace(tmp_path / "ws")
    shutil.copytree(ws0.root, ws.root)
    before = finished(ws)
    run_all(cfg, ws.root, scene)
    assert finished(ws) == before
    cfg2 = tmp_path / "wgs.toml"
    cfg2.write_text(cfg.read_text().replace("[fine]\niterations = 20", "[fine]\niterations = 12"))
    run_all(cfg2, ws.root, scene)
    after = finished(ws)
    changed = {s for s in STAGES if after[s] != before[s]}
    assert changed == {"fine", "eval"}
    assert ws.manifest("fine")["iterations"] == 12 and ws.manifest("fine")["rounds"] == 1
    # a second round: the refined model's renders repaired again, trained on again
    # from G_c instead of the visual hull (a masked scene's default)
    assert ws.manifest("fine")["start"] == "carved hull"  # the shipped S carved the hull in the repair stage
    res = CliRunner().invoke(
        cli,
        ["-q", "--config", str(cfg2), "-w", str(ws.root), "fine", "--rounds", "2", "--start", "coarse"],
        catch_exceptions=False,
    )
    assert res.exit_code == 0, res.output
    m = ws.manifest("fine")
    assert m["rounds"] == 2 and m["iterations"] == 12 and math.isfinite(m["final_loss"])
    assert m["start"] == "coarse"


def test_without_masks_and_test_views(tiny, tmp_path):
    from wgs.io.images import read_image, write_png

    scene, cfg, _, _ = tiny
    d = tmp_path / "nomask"
    shutil.copytree(scene, d)
    for p in d.rglob("*.png"):
        write_png(p, read_image(p)[..., :3])  # RGB only: no alpha, so no masks
    (d / "transforms_test.json").unlink()
    res = CliRunner().invoke(
        cli,
        ["--config", str(cfg), "-w", str(tmp_path / "ws"), "all", str(d), "--views", "4", "--masks", "none"],
        catch_exceptions=False,
    )
    assert res.exit_code == 0, res.output
    ws = Workspace(tmp_path / "ws")
    assert ws.manifest("fine")["start"] == "coarse"  # no masks, no visual hull: G_f starts from G_c
    # no test split in the dataset -> every 8th remaining view; here none remain: eval scores what the
    # scene can show, the fit at the training photos, and says so
    results = json.loads(ws.output("eval", "results").read_text())
    assert results["views"] == "training" and results["num_views"] == 4 and results["shape"] is None
    report = ws.output("eval", "report").read_text()
    assert "4 training views: there are no test views" in report
    out = " ".join(res.output.split())
    assert "no masks" in out and "no test views" in out


def test_many_views_leave_out_repair(tmp_path, tiny):
    _, cfg, _, _ = tiny
    scene = make_scene(tmp_path / "many", seed=3, size=32, n_train=12, n_test=2)
    res = CliRunner().invoke(
        cli, ["--config", str(cfg), "-w", str(tmp_path / "ws"), "all", str(scene)], catch_exceptions=False
    )
    assert res.exit_code == 0, res.output
    ws = Workspace(tmp_path / "ws")
    assert ws.manifest("mask_data") is None and ws.manifest("fine") is None
    r = json.loads((ws.root / "6_eval/results.json").read_text())
    assert r["final_model"] == "coarse"
    assert "--force-repair" in " ".join(res.output.split())


def chromium() -> str | None:
    return shutil.which("chromium") or shutil.which("chromium-browser") or shutil.which("google-chrome")


def drawn(shot) -> bool:
    """The viewer's canvas shows something: > 5 % non-white pixels below the title bar."""
    return bool((shot[120:360, 160:480].mean(-1) < 0.9).mean() > 0.05)


def screenshots(urls: list[str], tmp_path, done=lambda url, shot: True) -> list:
    """Headless Chromium (driven by Playwright, WebGL on SwiftShader: no GPU) pictures [H, W, 3] of
    each page once it says it is ready (the viewer sets body[data-ready]) and `done(url, shot)`
    holds (retried for up to 30 s: the depth sort runs in a worker, later on a busy machine)."""
    import time

    sync_playwright = pytest.importorskip("playwright.sync_api").sync_playwright
    from wgs.io.images import read_image

    if chromium() is None:
        pytest.skip("Chromium is not installed (apt install chromium): no screenshots")
    out = []
    with sync_playwright() as p:
        browser = p.chromium.launch(
            executable_path=chromium(),
            args=[
                "--no-sandbox",
                "--use-angle=swiftshader",
                "--enable-unsafe-swiftshader",
                "--disable-background-networking",
                "--disable-component-update",
                "--disable-sync",
            ],
        )
        try:
            page = browser.new_page(viewport={"width": 640, "height": 480})
            errors = []
            page.on("pageerror", lambda e: errors.append(e))
            for i, url in enumerate(urls):
                page.goto(url)
                page.wait_for_function(
                    "document.readyState === 'complete' && (!document.getElementById('canvas')"
                    " || document.body.dataset.ready)",
                    timeout=60000,
                )
                path = tmp_path / f"shot{i}.png"
                for _ in range(30):
                    time.sleep(1)
                    page.screenshot(path=str(path))
                    shot = read_image(path)[..., :3]
                    if done(url, shot):
                        break
                out.append(shot)
            assert not errors, errors
        finally:
            browser.close()
    return out


def test_viewer_serves_the_model_and_the_report(tiny, tmp_path):
    from urllib.error import HTTPError
    from urllib.request import urlopen

    from wgs.viewer import serving, site

    _, _, ws, _ = tiny
    files = site(ws, None)
    with serving(files) as url:
        assert url.startswith("http://127.0.0.1:")
        page = urlopen(url).read().decode()
        assert 'from "./gsplat.es.js"' in page
        with urlopen(url + "gsplat.es.js") as r:
            assert "javascript" in r.headers["Content-Type"] and b"PLYLoader" in r.read()
        view = json.loads(urlopen(url + "view.json").read())
        assert view["stage"] == "fine" and view["report"] is True and view["radius"] > 0
        assert len(urlopen(url + "model.splat").read()) == 32 * view["gaussians"]
        assert b"Per view" in urlopen(url + "report.html").read()
        assert b"MIT License" in urlopen(url + "LICENSE.gsplat").read()
        with pytest.raises(HTTPError):
            urlopen(url + "../scene/scene.json")
        viewer, report = screenshots(
            [url, url + "report.html"], tmp_path, done=lambda u, shot: u.endswith(".html") or drawn(shot)
        )
        assert drawn(viewer), "the viewer's canvas is blank"
        assert report.std() > 0.05 and (report.mean(-1) < 0.5).mean() > 0.005, "the report is blank"


def test_export_ply_and_splat(tiny, tmp_path):
    _, cfg, ws, _ = tiny
    for fmt in ("ply", "splat"):
        out = tmp_path / f"model.{fmt}"
        res = CliRunner().invoke(
            cli, ["-w", str(ws.root), "export", "--format", fmt, "-o", str(out)], catch_exceptions=False
        )
        assert res.exit_code == 0, res.output
        data = out.read_bytes()
        if fmt == "ply":
            header = data[: data.index(b"end_header")].decode()
            assert header.count("f_rest_") == 45
        else:
            assert len(data) % 32 == 0 and len(data) > 0


def test_fine_records_whether_its_lpips_term_ran(tiny):
    _, _, ws, _ = tiny
    term = ws.manifest("fine")["lpips_term"]
    assert term["used"] is False and "not found" in term["why"]


def sure_background_model(kind: str):
    """A tiny S or V that calls everything background, and sure of it."""
    import torch

    from wgs.models.silhouette_net import SilhouetteNet, SilhouetteNetConfig
    from wgs.models.volume_net import VolumeNet, VolumeNetConfig

    if kind == "S":
        net = SilhouetteNet(SilhouetteNetConfig(channels=8))
        last = net.out
    else:
        net = VolumeNet(VolumeNetConfig(channels=8, resolution=16))
        last = net.head[-1]
    torch.nn.init.zeros_(last.weight)
    torch.nn.init.constant_(last.bias, -8.0)
    return net


@pytest.mark.parametrize(
    "kind, setting, record", [("S", "silhouette_model", "carving"), ("V", "volume_model", "volume_carving")]
)
def test_a_carving_model_carves_the_hull_and_fine_starts_there(tiny, tmp_path, kind, setting, record):
    """With an S or a V at hand (here one that calls everything background), the repair stage writes
    the pseudo views' silhouettes and a carved hull that still covers every real mask pixel, and G_f
    starts from it. (V's own check is switched off here; `test_shape` tests it.)"""
    from wgs.models.storage import save_model
    from wgs.scene.dataset import load_prepared
    from wgs.shape.hull import load_grid, silhouette, visual_hull_grid

    scene, cfg, ws0, _ = tiny
    save_model(tmp_path / kind, sure_background_model(kind))
    ws = Workspace(tmp_path / "ws")
    shutil.copytree(ws0.root, ws.root)
    cfg2 = tmp_path / "wgs.toml"
    cfg2.write_text(
        cfg.read_text().replace("[repair]\n", f"[repair]\n{setting} = '{tmp_path / kind}'\nvolume_check_margin = 1.0\n")
    )
    run_all(cfg2, ws.root, scene)
    views = json.loads(ws.output("repair", "views").read_text())["views"]
    assert all((ws.stage_dir("repair") / v["silhouette"]).is_file() for v in views)
    counts = ws.manifest("repair")[record]
    assert counts["carved"] > 0 and counts["restored"] > 0  # the model wanted it all; the real masks kept some
    if kind == "V":  # the object's own check ran (such a V is near harmless after the rule: test_shape)
        assert counts["used"] and 0 < counts["leave_one_out_iou_carved"] <= 1 and 0 < counts["leave_one_out_iou"] <= 1
    assert ws.manifest("fine")["start"] == "carved hull"
    prepared = load_prepared(ws.stage_dir("prepare"))
    carved = load_grid(ws.output("repair", "carved_hull"))
    full = visual_hull_grid(prepared.train, carved.resolution, tolerate=0)
    for f in prepared.train:
        was = silhouette(full, f)[0] & (f.mask > 0.5)
        assert not (was & ~silhouette(carved, f)[0]).any()
    assert math.isfinite(json.loads((ws.stage_dir("eval") / "results.json").read_text())["psnr"])


@pytest.fixture(scope="module")
def mirrored(finished_workspace, tmp_path_factory):
    """The tiny scene run again with the default outline mirror views (the tests' TINY config has
    none); its 64 px masks miss 2.9 % under their mirror, so the gate is widened to let the views exist."""
    from conftest import TINY

    base, _ = finished_workspace
    root = tmp_path_factory.mktemp("mirrored")
    cfg = root / "wgs.toml"
    cfg.write_text(
        TINY.replace('mirror = "none"', 'mirror = "outline"\nmirror_directions = 60\nmirror_max_missed = 0.05')
    )
    run_all(cfg, root / "ws", base / "scene")
    return Workspace(root / "ws")


def test_the_mirror_check_and_the_carved_hull_are_reported(mirrored):
    """prepare looked for the object's mirror plane and kept its check; the photos' mirror images
    are training views that teach the outline only (no pairs, no U views); eval scores the carved
    hull at the test views beside the strict one and names the mirror's check."""
    from wgs.scene.dataset import load_prepared
    from wgs.stages.prepare.settings import PrepareConfig

    ws = mirrored
    summary = ws.manifest("prepare")["summary"]
    mirror = summary["mirror"]
    assert len(mirror["plane"]["normal"]) == 3 and 0 < mirror["leave_one_out_iou"] <= 1
    gain = mirror["leave_one_out_iou_mirrored"] - mirror["leave_one_out_iou"]
    cfg = PrepareConfig(**ws.manifest("prepare")["config"])
    assert mirror["used"] == (gain >= cfg.mirror_min_gain and mirror["missed"] <= cfg.mirror_max_missed)
    assert mirror["used"], mirror
    train = load_prepared(ws.stage_dir("prepare")).train
    assert len(train) == 2 * summary["num_train"]
    assert sum(f.name.endswith(".mirror.png") for f in train) == summary["num_train"]
    assert mirror["views"] == "outline" and all(f.shows_colour != f.name.endswith(".mirror.png") for f in train)
    photos = {f.name for f in train if f.shows_colour}
    index = json.loads(ws.output("mask_data", "index").read_text())
    assert {p["view"] for p in index["pairs"]} <= photos and set(index["hf_views"]) == photos
    shape = json.loads(ws.output("eval", "results").read_text())["shape"]
    assert shape["mirror"] == mirror and 0 < shape["carved_hull_test"]["iou"] <= 1
    report = ws.output("eval", "report").read_text()
    assert "carved hull" in report and "mirror images are training views (their outlines)" in report
    per_view = json.loads((ws.stage_dir("eval") / "per_view_shape.json").read_text())
    assert set(per_view["carved_hull_test"]) == set(per_view["hull_test"]) and per_view["hull_test"]
    assert len(per_view["leave_one_out"]) == summary["num_train"]  # the photos only


def test_masks_that_share_no_region_train_without_carving_or_hull_scores(tiny, tmp_path):
    """One training mask off the object (the hull that tolerates one bad mask still exists, the one
    every mask agrees on does not): the pipeline runs through, without carving and without the
    visual hull's scores, and says so."""
    from wgs.io.images import read_image, write_png

    scene, cfg, _, _ = tiny
    d = tmp_path / "scene"
    shutil.copytree(scene, d)
    img = read_image(d / "train" / "r_0.png")
    alpha = np.zeros(img.shape[:2], np.float32)
    alpha[:6, :6] = 1.0  # a corner the object never covers
    write_png(d / "train" / "r_0.png", np.concatenate([img[..., :3], alpha[..., None]], -1))
    res = run_all(cfg, tmp_path / "ws", d)
    ws = Workspace(tmp_path / "ws")
    assert ws.manifest("repair").get("carving") is None and ws.manifest("fine")["start"] == "hull"
    out = json.loads(ws.output("eval", "results").read_text())
    assert out["shape"] is None and math.isfinite(out["psnr"])
    assert res.exit_code == 0
