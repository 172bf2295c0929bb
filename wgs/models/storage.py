"""Models on disk: `config.json` + `model.safetensors` per model folder (no pickle)."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from typing import Any, TypeVar

import torch
from safetensors import SafetensorError
from safetensors.torch import load_file, save_file

from ..errors import InputError
from ..io import atomic_path, atomic_write_json
from .hf_unet import HFUNet, HFUNetConfig
from .ll_denoiser import LLDenoiser, LLDenoiserConfig
from .silhouette_net import SilhouetteNet, SilhouetteNetConfig
from .volume_net import VolumeNet, VolumeNetConfig

# class name in config.json -> (network, its config dataclass)
CLASSES: dict[str, tuple[type[torch.nn.Module], Any]] = {
    "LLDenoiser": (LLDenoiser, LLDenoiserConfig),
    "HFUNet": (HFUNet, HFUNetConfig),
    "SilhouetteNet": (SilhouetteNet, SilhouetteNetConfig),
    "VolumeNet": (VolumeNet, VolumeNetConfig),
}

M = TypeVar("M", bound=torch.nn.Module)


def config_of(model: torch.nn.Module) -> Any:
    """The config dataclass of a network of CLASSES (its `config` attribute)."""
    return vars(model)["config"]


def save_model(folder: Path, model: torch.nn.Module, extra: dict | None = None) -> None:
    folder.mkdir(parents=True, exist_ok=True)
    with atomic_path(folder / "model.safetensors") as tmp:
        save_file({k: v.detach().cpu().contiguous() for k, v in model.state_dict().items()}, str(tmp))
    config = model.config_dict()  # type: ignore[operator]  # every network of CLASSES has it
    atomic_write_json(folder / "config.json", {**config, **(extra or {})})


def load_model(folder: Path, device: torch.device | str = "cpu") -> tuple[torch.nn.Module, dict]:
    cfg_path, w_path = folder / "config.json", folder / "model.safetensors"
    try:
        cfg = json.loads(cfg_path.read_text())
    except FileNotFoundError:
        raise InputError("model config not found", cfg_path) from None
    except json.JSONDecodeError as exc:
        raise InputError(f"not valid JSON ({exc})", cfg_path) from None
    name = cfg.get("class") if isinstance(cfg, dict) else None
    if name not in CLASSES:
        raise InputError(f"unknown model class {name!r}", cfg_path)
    cls, cfg_cls = CLASSES[name]
    fields = {f.name: cfg[f.name] for f in dataclasses.fields(cfg_cls) if f.name in cfg}
    try:
        model = cls(cfg_cls(**fields))
    except (TypeError, ValueError, RuntimeError) as exc:
        raise InputError(
            f"model config does not describe a {name} ({str(exc).splitlines()[0][:160]})", cfg_path
        ) from None
    try:
        state = load_file(str(w_path))
        model.load_state_dict(state)
    except FileNotFoundError:
        raise InputError("model weights not found", w_path) from None
    except (SafetensorError, RuntimeError, OSError) as exc:
        raise InputError(f"weights do not fit the model ({str(exc).splitlines()[0][:200]})", w_path) from None
    return model.to(device).eval(), cfg


def load_model_of(folder: Path, cls: type[M], device: torch.device | str = "cpu") -> tuple[M, dict]:
    """`load_model` of a folder that must hold a `cls` (InputError naming its config otherwise)."""
    model, cfg = load_model(folder, device)
    if not isinstance(model, cls):
        raise InputError(f"holds a {type(model).__name__}, not a {cls.__name__}", folder / "config.json")
    return model, cfg
