"""Interruption: SIGKILL and Ctrl-C at a stage's middle, then a rerun; periodic state, --resume.

The slow version (kill points spread over every stage, a trial killed every few seconds) is
`make stress` (python -m tools.stress kill-loop).
"""

import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch
from conftest import TINY_ONE_MODEL, make_scene, run_wgs

import wgs.resume
from tools.stress import STACK_MARKERS, max_param_difference, outcome
from wgs.resume import Checkpointer, Interrupted
from wgs.stages.finetune.settings import FinetuneConfig
from wgs.training.per_object import train_hf_unet, train_scratch_d

pytestmark = pytest.mark.slow  # `pytest -m 'not slow'` for a quick loop; make test runs all

# TINY_ONE_MODEL with longer coarse and mask-data loops, so a kill lands in their middle; the coarse
# model trains all its iterations (tests/test_stopping.py resumes a stage that the held-out rule
# stopped, and an ensemble member killed in its loop)
CFG = (
    TINY_ONE_MODEL.replace(
        "iterations = 30\nrefine_start = 10\nrefine_every = 10",
        "iterations = 150\nrefine_start = 20\nrefine_every = 20",
    )
    .replace("warmup = 10\npair_every = 10", "warmup = 50\npair_every = 25")
    .replace("[coarse]\niterations = 150", "[coarse]\niterations = 100")
)
assert "[coarse]\niterations = 100" in CFG and "iterations = 150" in CFG and 'stop = "iterations"' in CFG


@pytest.fixture(scope="module")
def setup(tmp_path_factory):
    base = tmp_path_factory.mktemp("resume")
    scene = make_scene(base / "scene", seed=2, size=64, n_train=4, n_test=5)
    cfg = base / "wgs.toml"
    cfg.write_text(CFG)
    ref = base / "reference"
    assert run_wgs(wgs_args(ref, cfg, "all", str(scene)), base).returncode == 0
    return scene, cfg, ref


def copy_workspace(src: Path, ws: Path, folders: tuple[str, ...] = ("scene",)) -> Path:
    """A workspace `ws` holding the stage `folders` of the workspace `src` and its run record (the
    same inputs and settings), so that a test starts at the next stage without running those again."""
    ws.mkdir(parents=True)
    for folder in folders:
        shutil.copytree(src / folder, ws / folder)
    shutil.copy(src / "run.json", ws / "run.json")
    return ws


def prepared_copy(setup, tmp_path, done: tuple[str, ...] = ("scene",)) -> Path:
    """tmp_path/ws holding the reference run's stage folders `done` (its prepared scene by default)."""
    return copy_workspace(setup[2], tmp_path / "ws", done)


def wgs_args(ws: Path, cfg: Path, *args: str, resume: bool = False, quiet: bool = True) -> list[str]:
    """`wgs`'s arguments for a run in `ws` with the config `cfg` (`run_wgs` runs them in this process)."""
    return [
        *(["-q"] if quiet else []),
        "--config",
        str(cfg),
        "--checkpoint-every",
        "0",
        *(["--resume"] if resume else []),
        "-w",
        str(ws),
        *args,
    ]


def wgs_cmd(ws: Path, cfg: Path, *args: str, resume: bool = False, quiet: bool = True) -> list[str]:
    """`wgs_args` as a command for a subprocess: for the runs a test interrupts with a signal."""
    return [sys.executable, "-m", "wgs", *wgs_args(ws, cfg, *args, resume=resume, quiet=quiet)]


def start_and_signal_when(cmd: list[str], trigger: Path, sig: int, timeout: float = 120) -> subprocess.Popen:
    """Start `cmd`; send `sig` as soon as `trigger` exists (a loop saved its state)."""
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    t0 = time.monotonic()
    while not trigger.exists():
        if proc.poll() is not None:
            raise AssertionError(f"finished before {trigger.name} appeared: {proc.stderr.read()}")
        if time.monotonic() - t0 > timeout:
            proc.kill()
            raise AssertionError(f"{trigger} never appeared")
        time.sleep(0.02)
    proc.send_signal(sig)
    return proc


def assert_same_model(ws: Path, ref: Path, folder: str = "1_coarse") -> None:
    """The stage `folder`'s model in `ws` equals the one in `ref`, bit for bit."""
    a = torch.load(ws / folder / "ckpt.pt", weights_only=True)["splats"]
    b = torch.load(ref / folder / "ckpt.pt", weights_only=True)["splats"]
    assert all(torch.equal(a[k], b[k]) for k in b)


def test_sigkill_in_mask_data_then_resume_gives_the_uninterrupted_result(setup, tmp_path):
    """`wgs all` killed in mask-data, its prepare and coarse stages done (the reference run's);
    `wgs --resume all` ends with the reference run's models."""
    scene, cfg, ref = setup
    ws = prepared_copy(setup, tmp_path, ("scene", "1_coarse"))
    proc = start_and_signal_when(wgs_cmd(ws, cfg, "all", str(scene)), ws / ".resume/2_mask_data/gd.pt", signal.SIGKILL)
    proc.wait()
    assert proc.returncode == -signal.SIGKILL
    assert (ws / "1_coarse/manifest.json").exists() and not (ws / "2_mask_data").exists()
    saved = torch.load(ws / ".resume/2_mask_data/gd.pt", weights_only=True)
    assert 0 < saved["it"] < 150
    res = run_wgs(wgs_args(ws, cfg, "all", str(scene), resume=True), tmp_path)
    assert res.returncode == 0, res.stderr
    assert outcome(ws) == outcome(ref)
    assert max_param_difference(ws, ref) == 0.0
    assert not (ws / ".resume").exists()  # cleaned up once every stage finished


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGUSR1])
def test_ctrl_c_saves_state_with_one_line_and_resume_continues(setup, tmp_path, sig):
    """Ctrl-C, or Slurm's --signal=USR1, in `wgs coarse`: the loop saves, one line, exit 128 + the
    signal; `wgs --resume coarse` ends with the uninterrupted run's model. (SIGUSR2, submitit's,
    takes the same handler: `make test-cluster` sends it to a training job through Slurm.)"""
    _, cfg, ref = setup
    ws = prepared_copy(setup, tmp_path)
    proc = start_and_signal_when(wgs_cmd(ws, cfg, "coarse"), ws / ".resume/1_coarse/gc.pt", sig)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 128 + sig
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("interrupted: coarse stopped after step"), err
    assert "--resume" in lines[0] and "Traceback" not in err
    assert sig == signal.SIGINT or f"({sig.name})" in lines[0]
    stopped = torch.load(ws / ".resume/1_coarse/gc.pt", weights_only=True)["it"]
    assert 0 < stopped < 100 and not (ws / "1_coarse").exists()
    res = run_wgs(wgs_args(ws, cfg, "coarse", resume=True), tmp_path)
    assert res.returncode == 0, res.stderr
    assert_same_model(ws, ref)


def test_a_scheduler_stop_signal_saves_with_one_line_and_resume_finishes_identically(setup, tmp_path):
    """Slurm's SIGTERM in `wgs all`, whose prepare stage loaded pycolmap (its glog answers SIGTERM
    with a native stack trace unless wgs puts its own handler back): the loop saves, one line, exit
    128 + the signal; `wgs --resume coarse` ends with the uninterrupted run's G_c (a resumed `wgs
    all` to the end: the SIGKILL test above). (SIGUSR1, which glog leaves alone, in the test above;
    `python -m tools.stress signal-loop` sends each signal at 10 random moments.)"""
    scene, cfg, ref = setup
    sig = signal.SIGTERM
    ws = tmp_path / "ws"
    proc = start_and_signal_when(wgs_cmd(ws, cfg, "all", str(scene)), ws / ".resume/1_coarse/gc.pt", sig)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 128 + sig, err
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("interrupted: coarse stopped after step"), err
    assert f"({sig.name})" in lines[0] and "--resume" in lines[0]
    assert not any(m in err for m in STACK_MARKERS), err
    res = run_wgs(wgs_args(ws, cfg, "coarse", resume=True), tmp_path)
    assert res.returncode == 0, res.stderr
    assert_same_model(ws, ref)


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGUSR1, signal.SIGUSR2])
def test_a_stop_signal_outside_a_loop_stops_at_once_after_pycolmap_loaded(sig):
    code = (
        "import os, signal, time\n"
        "from wgs.resume import Stopped, install_stop_handlers\n"
        "install_stop_handlers()\n"
        "import wgs.scene.colmap  # pycolmap: its glog installs a native handler on import\n"
        "try:\n"
        f"    os.kill(os.getpid(), {int(sig)}); time.sleep(10)\n"
        "except Stopped as exc:\n"
        "    print('stopped', exc.signum)\n"
    )
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert res.returncode == 0 and res.stdout.strip() == f"stopped {int(sig)}", res.stdout + res.stderr
    assert not any(m in res.stderr for m in STACK_MARKERS), res.stderr


def coarse_killed_midway(setup, tmp_path) -> Path:
    """A prepared workspace whose coarse stage was SIGKILLed after its first saved state."""
    _, cfg, _ = setup
    ws = prepared_copy(setup, tmp_path)
    proc = start_and_signal_when(wgs_cmd(ws, cfg, "coarse"), ws / ".resume/1_coarse/gc.pt", signal.SIGKILL)
    proc.wait()
    return ws


def test_saved_state_of_other_settings_is_not_resumed(setup, tmp_path):
    _, cfg, _ = setup
    ws = coarse_killed_midway(setup, tmp_path)
    res = run_wgs(wgs_args(ws, cfg, "coarse", "--iterations", "40", resume=True, quiet=False), tmp_path)
    assert res.returncode == 0, res.stderr
    assert "belongs to other inputs or settings: starting over" in res.stderr
    assert torch.load(ws / "1_coarse/ckpt.pt", weights_only=True)["step"] == 40


def test_without_resume_a_rerun_starts_over_and_says_so(setup, tmp_path):
    _, cfg, _ = setup
    ws = coarse_killed_midway(setup, tmp_path)
    res = run_wgs(wgs_args(ws, cfg, "coarse", quiet=False), tmp_path)
    assert res.returncode == 0, res.stderr
    assert "starting over (add --resume" in res.stderr


# ----------------------------------------------------------------------------- the finetune loops, in process
def interrupt_at(monkeypatch, at: int) -> None:
    """Make check_interrupt see a Ctrl-C once the loop reached step `at`."""
    calls = {"n": 0}

    def fake() -> bool:
        calls["n"] += 1
        return calls["n"] == at

    monkeypatch.setattr(wgs.resume, "stop_requested", fake)


@pytest.mark.parametrize("loop", ["D", "U"])
def test_finetune_loops_resume_exactly(loop, tmp_path, monkeypatch):
    cfg = FinetuneConfig(
        d_steps=12,
        d_channels=8,
        d_batch=2,
        d_crop=16,
        u_max_steps=12,
        u_channels=8,
        u_batch=2,
        u_crop=8,
        u_eval_every=3,
        u_patience=100,
    )
    g = torch.Generator().manual_seed(0)
    a, b = torch.rand(6, 3, 32, 32, generator=g) * 2 - 1, torch.rand(6, 3, 32, 32, generator=g) * 2 - 1

    def train(ck):
        torch.manual_seed(0)
        gen = torch.Generator().manual_seed(1)
        if loop == "D":
            return train_scratch_d(cfg, a, b, torch.device("cpu"), gen, ck)[:2]
        return train_hf_unet(cfg, a, b, torch.device("cpu"), gen, ck)

    def timeless(curve):
        return {k: v for k, v in curve.items() if k != "seconds"}

    ref_model, ref_curve = train(None)
    interrupt_at(monkeypatch, 5)
    with pytest.raises(Interrupted, match="stopped after step 5"):
        train(Checkpointer(tmp_path / "s.pt", every_s=1e9, resume=False))
    monkeypatch.setattr(wgs.resume, "stop_requested", lambda: False)
    model, curve = train(Checkpointer(tmp_path / "s.pt", every_s=1e9, resume=True))
    assert timeless(curve) == timeless(ref_curve)
    for (k, p), q in zip(model.state_dict().items(), ref_model.state_dict().values(), strict=True):
        assert torch.equal(p, q), k


def test_damaged_resume_state_is_a_clear_error(tmp_path):
    path = tmp_path / "gc.pt"
    path.write_bytes(b"PK\x03\x04 truncated")
    with pytest.raises(wgs.errors.WgsError, match="cannot read the resume checkpoint"):
        Checkpointer(path, 0, resume=True).load()


def test_deferred_stop_second_ctrl_c_stops_at_once():
    # the handler from before comes back: default_int_handler, or SIG_IGN in a background job
    before = signal.getsignal(signal.SIGINT)
    with wgs.resume.deferred_stop():
        os.kill(os.getpid(), signal.SIGINT)
        time.sleep(0.01)
        assert wgs.resume.stop_requested()
        with pytest.raises(KeyboardInterrupt):
            os.kill(os.getpid(), signal.SIGINT)
            time.sleep(0.01)
    assert not wgs.resume.stop_requested()
    assert signal.getsignal(signal.SIGINT) is before


def one_view_and_splats():
    """A 16 px photo and 40 Gaussians: a loop of a few iterations."""
    from conftest import ring_w2c

    from wgs.gaussians.splats import create_splats
    from wgs.scene.dataset import Frame

    f = Frame(
        torch.tensor([[20.0, 0, 8], [0, 20, 8], [0, 0, 1]]),
        torch.tensor(ring_w2c()[0], dtype=torch.float32),
        16,
        16,
        name="a.png",
        image=torch.rand(16, 16, 3, generator=torch.Generator().manual_seed(0)),
    )
    return f, create_splats(torch.randn(40, 3) * 0.1, torch.rand(40, 3), torch.full((40,), 0.05), 0)


def test_a_finished_loop_resumes_to_its_result_without_moments(tmp_path):
    """Killed after training, before the outputs were written: the final state holds the model only."""
    from wgs.gaussians.trainer import TrainConfig, train_gaussians

    f, sp = one_view_and_splats()
    cfg = TrainConfig(iterations=6, refine_start=100, floater_every=0, log_every=1)
    first = train_gaussians(
        sp,
        [f],
        cfg,
        torch.device("cpu"),
        extent=1.0,
        has_masks=False,
        checkpoint=Checkpointer(tmp_path / "s.pt", every_s=1e9, resume=False),
    )
    saved = torch.load(tmp_path / "s.pt", weights_only=True)
    assert saved["finished"] and "optimizers" not in saved
    again = train_gaussians(
        sp,
        [f],
        cfg,
        torch.device("cpu"),
        extent=1.0,
        has_masks=False,
        checkpoint=Checkpointer(tmp_path / "s.pt", every_s=1e9, resume=True),
    )
    assert again.iterations == first.iterations == 6 and again.losses == first.losses
    assert all(torch.equal(again.splats[k], first.splats[k]) for k in first.splats)


def test_a_loop_carries_on_from_a_kept_state_as_one_loop_would():
    """A loop's state kept at its end with the moments (`keep_state`, as a coarse pilot's) and
    carried on (`start`) on the same photo: the model of one loop over all the iterations; the
    carried loop counts its own losses. Where the views differ (a pilot's member) only the views'
    order starts over."""
    import dataclasses

    from wgs.gaussians.trainer import TrainConfig, train_gaussians

    f, sp = one_view_and_splats()
    cpu = torch.device("cpu")
    cfg = TrainConfig(iterations=12, refine_start=100, floater_every=0, log_every=1)
    torch.manual_seed(0)
    whole = train_gaussians(sp, [f], cfg, cpu, extent=1.0, has_masks=False)
    torch.manual_seed(0)
    early = dataclasses.replace(cfg, end_iteration=5)
    first = train_gaussians(sp, [f], early, cpu, extent=1.0, has_masks=False, keep_state=True)
    assert first.state is not None and first.state["it"] == 5
    assert float(first.state["optimizers"]["means"]["state"][0]["step"]) == 5  # the moments travel
    fresh = {k: torch.zeros_like(v) for k, v in sp.items()}  # not used: the kept state's are
    rest = train_gaussians(fresh, [f], cfg, cpu, extent=1.0, has_masks=False, start=first.state)
    assert rest.iterations == 12 and len(rest.losses) == 7
    assert all(torch.equal(rest.splats[k], whole.splats[k]) for k in whole.splats)
