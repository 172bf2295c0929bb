"""Novel viewpoints come from the training cameras only."""

import torch
from conftest import make_scene

from wgs.scene.dataset import Frame
from wgs.scene.orbit import look_at, novel_views, sphere_views


def ring(n=4, radius=1.0, height=0.3):
    import math

    import numpy as np

    K = torch.tensor([[50.0, 0, 32], [0, 50, 32], [0, 0, 1]])
    out = []
    for i in range(n):
        a = 2 * math.pi * i / n + 0.1 * i
        eye = np.array([radius * math.cos(a), radius * math.sin(a), height])
        out.append(
            Frame(
                K,
                torch.tensor(look_at(eye, eye * 0, np.array([0, 0, 1.0])), dtype=torch.float32),
                64,
                64,
                name=f"t{i}.png",
            )
        )
    return out


def test_novel_views_between_neighbours_look_at_centre():
    train = ring()
    views = novel_views(train, 2, seed=0)
    assert len(views) == 8
    for f, dist in views:
        c = f.center
        assert abs(float(c.norm()) - float(train[0].center.norm())) < 0.05
        fwd = f.viewmat[2, :3]
        torch.testing.assert_close(fwd, -c / c.norm(), atol=1e-5, rtol=0)  # looks at the origin
        assert dist > 0.05


def test_sphere_views_cover_a_band_at_the_training_distance():
    import math

    import numpy as np

    from wgs.scene.orbit import fit_orbit

    train = ring(radius=1.0, height=0.3)  # cameras near elevation atan(0.3) = 16.7 degrees
    views = sphere_views(train, 24, below_deg=15, above_deg=25)
    up = torch.tensor(fit_orbit(train).up, dtype=torch.float32)

    def elevation(c):
        return math.degrees(math.asin(float(c @ up / c.norm())))

    t_elev = [elevation(t.center) for t in train]
    assert np.ptp(t_elev) < 5
    assert len(views) == 24 and len({f.name for f, _ in views}) == 24
    elev = []
    for f, dist in views:
        c = f.center
        assert abs(float(c.norm()) - float(train[0].center.norm())) < 1e-4
        torch.testing.assert_close(f.viewmat[2, :3], -c / c.norm(), atol=1e-5, rtol=0)  # looks at the origin
        near = min(float((c - t.center).norm()) for t in train)
        assert abs(dist - near) < 1e-5
        elev.append(elevation(c))
    lo, hi = min(t_elev) - 15, max(t_elev) + 25
    assert lo - 1e-3 <= min(elev) and max(elev) <= hi + 1e-3
    assert max(elev) - min(elev) > 0.8 * (hi - lo)  # the band is covered, not one ring
    # azimuths spread: every quadrant has views
    quads = {(float(f.center[0]) > 0, float(f.center[1]) > 0) for f, _ in views}
    assert len(quads) == 4


def test_novel_views_do_not_depend_on_test_cameras(tmp_path):
    """Prepare twice with a test camera moved: everything before eval is identical."""
    import json
    import shutil

    import numpy as np
    from click.testing import CliRunner

    from wgs.cli import cli
    from wgs.scene.dataset import load_prepared
    from wgs.workspace import Workspace

    a = make_scene(tmp_path / "a", seed=4, size=32, n_train=4, n_test=3)
    b = tmp_path / "b"
    shutil.copytree(a, b)
    meta = json.loads((b / "transforms_test.json").read_text())
    m = np.asarray(meta["frames"][0]["transform_matrix"])
    m[:3, 3] *= 3.0  # move a test camera far away
    meta["frames"][0]["transform_matrix"] = m.tolist()
    (b / "transforms_test.json").write_text(json.dumps(meta))
    poses = []
    for src, ws in ((a, tmp_path / "wa"), (b, tmp_path / "wb")):
        assert CliRunner().invoke(cli, ["-q", "-w", str(ws), "prepare", str(src)]).exit_code == 0
        sc = load_prepared(Workspace(ws).stage_dir("prepare"))
        assert sc.norm.to_json() == load_prepared(Workspace(tmp_path / "wa").stage_dir("prepare")).norm.to_json()
        poses.append([f.viewmat for f, _ in novel_views(sc.train, 2, seed=0)])
    for p, q in zip(*poses, strict=True):
        assert torch.equal(p, q)
