"""The pretrained path for GPU users: Stable Diffusion 1.5 + ControlNet-tile from local folders,
fine-tuned with LoRA on the LL pairs (GaussianObject's recipe: rank 64, lr 1e-3, a rare-token prompt).

Optional extra `wgs[diffusers]`; diffusers is imported lazily (it takes seconds). Nothing is
downloaded: folders are opened with `local_files_only=True` (HF_HUB_OFFLINE is respected too).
LL subbands (in [0, 2]) are shown to Stable Diffusion as images LL/2 in [0, 1].
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch

from ..errors import InputError, WgsError
from ..io import atomic_path, atomic_write_json

PROMPT = "a photo of xxy5syt00"  # a rare token, as GaussianObject
SD_FILES = (
    "model_index.json",
    "unet/config.json",
    "vae/config.json",
    "text_encoder/config.json",
    "tokenizer/",
    "scheduler/scheduler_config.json",
)
CN_FILES = ("config.json",)


@dataclass
class LoraConfigLite:
    rank: int = 64
    lr: float = 1e-3
    steps: int = 500
    batch: int = 1


def require_diffusers():
    try:
        import diffusers  # noqa: F401
        import peft  # noqa: F401
    except ImportError as exc:
        raise WgsError(
            f"--diffusion controlnet needs the optional extra: pip install 'wgs[diffusers]' ({exc})"
        ) from None


def check_folders(sd_model: Path, controlnet: Path) -> None:
    """A clear message naming the files to download on a machine with internet."""
    for folder, files, what in (
        (sd_model, SD_FILES, "Stable Diffusion 1.5 (e.g. the runwayml/stable-diffusion-v1-5 folder layout)"),
        (controlnet, CN_FILES, "ControlNet tile (lllyasviel/control_v11f1e_sd15_tile)"),
    ):
        missing = [
            f for f in files if not ((Path(folder) / f).is_dir() if f.endswith("/") else (Path(folder) / f).is_file())
        ]
        if missing:
            raise InputError(
                f"missing {', '.join(missing)}: download {what} with its weights on a machine with "
                "internet and copy the folder here",
                folder,
            )


def load_pipeline(sd_model: Path, controlnet: Path, device: torch.device):
    """StableDiffusionControlNetImg2ImgPipeline from local folders, DDIM scheduler, no safety checker."""
    require_diffusers()
    check_folders(sd_model, controlnet)
    from diffusers import ControlNetModel, DDIMScheduler, StableDiffusionControlNetImg2ImgPipeline

    cn = ControlNetModel.from_pretrained(str(controlnet), local_files_only=True)
    pipe = StableDiffusionControlNetImg2ImgPipeline.from_pretrained(
        str(sd_model), controlnet=cn, safety_checker=None, requires_safety_checker=False, local_files_only=True
    )
    pipe.scheduler = DDIMScheduler.from_config(pipe.scheduler.config)
    pipe.set_progress_bar_config(disable=True)
    return pipe.to(device)


def add_lora(pipe, rank: int) -> list[torch.nn.Parameter]:
    """LoRA adapters on the UNet's attention projections; returns the trainable parameters."""
    from peft import LoraConfig

    pipe.unet.requires_grad_(False)
    pipe.vae.requires_grad_(False)
    pipe.text_encoder.requires_grad_(False)
    pipe.controlnet.requires_grad_(False)
    pipe.unet.add_adapter(
        LoraConfig(
            r=rank, lora_alpha=rank, init_lora_weights="gaussian", target_modules=["to_k", "to_q", "to_v", "to_out.0"]
        )
    )
    return [p for p in pipe.unet.parameters() if p.requires_grad]


def encode_prompt(pipe, batch: int) -> torch.Tensor:
    length = min(pipe.tokenizer.model_max_length, pipe.text_encoder.config.max_position_embeddings)
    tok = pipe.tokenizer(
        [PROMPT] * batch, padding="max_length", max_length=length, truncation=True, return_tensors="pt"
    )
    with torch.no_grad():
        return pipe.text_encoder(tok.input_ids.to(pipe.device))[0]


def lora_step(pipe, params, opt, clean: torch.Tensor, corrupted: torch.Tensor, gen: torch.Generator) -> float:
    """One LoRA step. clean, corrupted: [B, 3, H, W] images in [0, 1] (LL / 2)."""
    with torch.no_grad():
        latents = pipe.vae.encode(clean * 2 - 1).latent_dist.sample(gen) * pipe.vae.config.scaling_factor
    noise = torch.randn(latents.shape, generator=gen).to(latents)
    t = torch.randint(pipe.scheduler.config.num_train_timesteps, (latents.shape[0],), generator=gen).to(pipe.device)
    noisy = pipe.scheduler.add_noise(latents, noise, t)
    ehs = encode_prompt(pipe, latents.shape[0])
    down, mid = pipe.controlnet(noisy, t, encoder_hidden_states=ehs, controlnet_cond=corrupted, return_dict=False)
    pred = pipe.unet(
        noisy, t, encoder_hidden_states=ehs, down_block_additional_residuals=down, mid_block_additional_residual=mid
    ).sample
    target = (
        noise if pipe.scheduler.config.prediction_type == "epsilon" else pipe.scheduler.get_velocity(latents, noise, t)
    )
    loss = torch.nn.functional.mse_loss(pred.float(), target.float())
    opt.zero_grad(set_to_none=True)
    loss.backward()
    opt.step()
    return float(loss)


def save_lora(folder: Path, pipe, meta: dict[str, Any]) -> None:
    from peft.utils import get_peft_model_state_dict
    from safetensors.torch import save_file

    folder.mkdir(parents=True, exist_ok=True)
    state = {k: v.detach().cpu().contiguous() for k, v in get_peft_model_state_dict(pipe.unet).items()}
    with atomic_path(folder / "lora.safetensors") as tmp:
        save_file(state, str(tmp))
    atomic_write_json(folder / "config.json", {"class": "ControlNetLoRA", "prompt": PROMPT, **meta})


def load_lora(folder: Path, device: torch.device):
    """The pipeline of a saved LoRA fine-tune (paths recorded in its config.json)."""
    from peft.utils import set_peft_model_state_dict
    from safetensors.torch import load_file

    cfg = json.loads((folder / "config.json").read_text())
    pipe = load_pipeline(Path(cfg["sd_model"]), Path(cfg["controlnet"]), device)
    add_lora(pipe, cfg["rank"])
    set_peft_model_state_dict(pipe.unet, load_file(str(folder / "lora.safetensors")))
    pipe.unet.eval()
    return pipe, cfg


@torch.no_grad()
def repair(pipe, corrupted: torch.Tensor, strength: float, steps: int, seed: int = 0) -> torch.Tensor:
    """corrupted [B, 3, H, W] in [0, 1] -> repaired images [B, 3, H, W] in [0, 1] (img2img + ControlNet)."""
    gen = torch.Generator().manual_seed(seed)
    out = pipe(
        prompt=[PROMPT] * corrupted.shape[0],
        image=corrupted,
        control_image=corrupted,
        strength=strength,
        num_inference_steps=steps,
        guidance_scale=1.0,
        generator=gen,
        output_type="pt",
        height=corrupted.shape[-2],
        width=corrupted.shape[-1],
    ).images
    return out.float().cpu()
