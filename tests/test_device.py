"""Device selection and the line that names the rasterizer a run uses."""

import pytest
import torch

import wgs.context as context_module
from wgs.context import RunOptions
from wgs.device import resolve_device
from wgs.errors import WgsError


def test_cpu_is_always_there():
    assert resolve_device("cpu") == torch.device("cpu")


def test_an_unknown_device_is_one_clear_error():
    with pytest.raises(WgsError, match="unknown device"):
        resolve_device("tpu")


@pytest.mark.skipif(torch.cuda.is_available(), reason="checks the refusal on a machine without CUDA")
def test_cuda_without_cuda_is_refused():
    with pytest.raises(WgsError, match="CUDA is not available"):
        resolve_device("cuda")


@pytest.mark.parametrize(
    "device, has_gsplat, expect",
    [
        ("cpu", False, "rasterizer: numba"),
        ("cuda", False, "rasterizer: torch (the reference"),
        ("cuda", True, "rasterizer: gsplat"),
    ],
)
def test_the_device_line_names_the_rasterizer(monkeypatch, device, has_gsplat, expect):
    import wgs.device
    import wgs.gaussians.render as render

    lines = []
    monkeypatch.setattr(context_module, "log", lines.append)
    monkeypatch.setattr(wgs.device, "resolve_device", lambda spec: torch.device(device))
    monkeypatch.setattr(render, "_has_gsplat", lambda: has_gsplat)
    RunOptions(workspace=None, device=device, seed=0, debug=False).torch_device()
    assert lines and expect in lines[0]
    assert ("wgs[cuda]" in lines[0]) == (expect.startswith("rasterizer: torch"))
