"""LPIPS (Zhang et al. 2018) in plain torch, AlexNet and VGG16 variants, from local weights only.

Backbones are torchvision-format checkpoints (`alexnet-owt-7be5be79.pth`, `vgg16-397923af.pth`),
the linear layers are the LPIPS package's v0.1 files (`alex.pth`, `vgg.pth`). They are looked up
in, in order: an explicit folder, `$WGS_LPIPS_WEIGHTS`, `$TORCH_HOME/hub/checkpoints`
(default `~/.cache/torch/hub/checkpoints`), and for the linear layers an installed `lpips`
package's own `weights/v0.1/`. Nothing is ever downloaded.
"""

from __future__ import annotations

import os
from pathlib import Path

import torch
from torch import nn

BACKBONE_FILES = {"alex": "alexnet-owt-7be5be79.pth", "vgg": "vgg16-397923af.pth"}
LIN_FILES = {"alex": "alex.pth", "vgg": "vgg.pth"}
CHANNELS = {"alex": (64, 192, 384, 256, 256), "vgg": (64, 128, 256, 512, 512)}
# indices in the torchvision `features` Sequential after which a feature map is tapped (ReLU outputs)
TAPS = {"alex": (1, 4, 7, 9, 11), "vgg": (3, 8, 15, 22, 29)}
SHIFT = (-0.030, -0.088, -0.188)
SCALE = (0.458, 0.448, 0.450)


class LpipsUnavailable(Exception):
    """The weights are not on this machine; the message says which files to put where."""


def _features(net: str) -> nn.Sequential:
    if net == "alex":
        return nn.Sequential(
            nn.Conv2d(3, 64, 11, 4, 2),
            nn.ReLU(),
            nn.MaxPool2d(3, 2),
            nn.Conv2d(64, 192, 5, padding=2),
            nn.ReLU(),
            nn.MaxPool2d(3, 2),
            nn.Conv2d(192, 384, 3, padding=1),
            nn.ReLU(),
            nn.Conv2d(384, 256, 3, padding=1),
            nn.ReLU(),
            nn.Conv2d(256, 256, 3, padding=1),
            nn.ReLU(),
            nn.MaxPool2d(3, 2),
        )
    layers: list[nn.Module] = []
    cin = 3
    for v in (64, 64, "M", 128, 128, "M", 256, 256, 256, "M", 512, 512, 512, "M", 512, 512, 512, "M"):
        if v == "M":
            layers.append(nn.MaxPool2d(2, 2))
        else:
            layers += [nn.Conv2d(cin, int(v), 3, padding=1), nn.ReLU()]
            cin = int(v)
    return nn.Sequential(*layers)


def search_dirs(explicit: str | Path | None = None) -> list[Path]:
    dirs = []
    if explicit:
        dirs.append(Path(explicit))
    if os.environ.get("WGS_LPIPS_WEIGHTS"):
        dirs.append(Path(os.environ["WGS_LPIPS_WEIGHTS"]))
    torch_home = Path(os.environ.get("TORCH_HOME", Path.home() / ".cache" / "torch"))
    dirs.append(torch_home / "hub" / "checkpoints")
    dirs += lpips_package_dirs()
    return dirs


def lpips_package_dirs() -> list[Path]:
    """The linear layers inside an installed `lpips` package (`lpips/weights/v0.1/alex.pth`), found
    without importing it (its import pulls in torchvision)."""
    import importlib.util

    try:
        spec = importlib.util.find_spec("lpips")
    except (ImportError, ValueError):
        return []
    if spec is None or not spec.submodule_search_locations:
        return []
    return [Path(loc) / "weights" / "v0.1" for loc in spec.submodule_search_locations]


def _find(name: str, dirs: list[Path]) -> Path | None:
    return next((d / name for d in dirs if (d / name).is_file()), None)


class LPIPS(nn.Module):
    shift: torch.Tensor  # buffers: the input normalisation
    scale: torch.Tensor

    def __init__(self, net: str = "alex", weights_dir: str | Path | None = None):
        super().__init__()
        if net not in BACKBONE_FILES:
            raise ValueError(f"net must be 'alex' or 'vgg', got {net!r}")
        dirs = search_dirs(weights_dir)
        bb, lin = _find(BACKBONE_FILES[net], dirs), _find(LIN_FILES[net], dirs)
        if bb is None or lin is None:
            missing = [f for f, p in ((BACKBONE_FILES[net], bb), (LIN_FILES[net], lin)) if p is None]
            raise LpipsUnavailable(
                f"LPIPS-{net} weights not found ({', '.join(missing)} in {', '.join(map(str, dirs))}); on a machine "
                "with internet, get the torchvision backbone and the LPIPS v0.1 linear layers and copy them there"
            )
        self.net = net
        self.features = _features(net)
        state = torch.load(bb, map_location="cpu", weights_only=True)
        self.features.load_state_dict({k[len("features.") :]: v for k, v in state.items() if k.startswith("features.")})
        lin_state = torch.load(lin, map_location="cpu", weights_only=True)
        self.lins = nn.ModuleList()
        for i, ch in enumerate(CHANNELS[net]):
            conv = nn.Conv2d(ch, 1, 1, bias=False)
            conv.weight.data.copy_(lin_state[f"lin{i}.model.1.weight"])
            self.lins.append(conv)
        self.register_buffer("shift", torch.tensor(SHIFT)[None, :, None, None])
        self.register_buffer("scale", torch.tensor(SCALE)[None, :, None, None])
        self.sources = {"backbone": str(bb), "linear": str(lin)}
        self.eval().requires_grad_(False)

    def _taps(self, x: torch.Tensor) -> list[torch.Tensor]:
        out = []
        taps = TAPS[self.net]
        for i, layer in enumerate(self.features):
            x = layer(x)
            if i in taps:
                out.append(x)
            if i >= taps[-1]:
                break
        return out

    def forward(self, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
        """a, b: [B, 3, H, W] in [0, 1] -> [B] distances."""
        fa = self._taps((a * 2 - 1 - self.shift) / self.scale)
        fb = self._taps((b * 2 - 1 - self.shift) / self.scale)
        total = torch.zeros(a.shape[0], device=a.device)
        for lin, x, y in zip(self.lins, fa, fb, strict=True):
            x = x / (x.pow(2).sum(1, keepdim=True).sqrt() + 1e-10)
            y = y / (y.pow(2).sum(1, keepdim=True).sqrt() + 1e-10)
            total = total + lin((x - y) ** 2).mean(dim=(1, 2, 3))
        return total
