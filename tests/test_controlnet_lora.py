"""The Stable Diffusion + ControlNet + LoRA path on a tiny random pipeline built offline."""

import json

import pytest
import torch
from conftest import make_scene

from wgs.errors import InputError
from wgs.models import controlnet_lora as cl


def build_tiny_sd(root):
    """A random SD-1.5-shaped pipeline and ControlNet, saved like the real folders (no download)."""
    from diffusers import AutoencoderKL, ControlNetModel, DDIMScheduler, StableDiffusionPipeline, UNet2DConditionModel
    from transformers import CLIPTextConfig, CLIPTextModel, CLIPTokenizer

    torch.manual_seed(0)
    unet = UNet2DConditionModel(
        block_out_channels=(8, 16),
        layers_per_block=1,
        sample_size=4,
        in_channels=4,
        out_channels=4,
        down_block_types=("CrossAttnDownBlock2D", "DownBlock2D"),
        up_block_types=("UpBlock2D", "CrossAttnUpBlock2D"),
        cross_attention_dim=16,
        norm_num_groups=4,
        attention_head_dim=2,
    )
    vae = AutoencoderKL(
        block_out_channels=(4, 4, 4, 4),
        in_channels=3,
        out_channels=3,
        latent_channels=4,
        down_block_types=("DownEncoderBlock2D",) * 4,
        up_block_types=("UpDecoderBlock2D",) * 4,
        norm_num_groups=2,
        layers_per_block=1,
    )
    text = CLIPTextModel(
        CLIPTextConfig(
            bos_token_id=0,
            eos_token_id=1,
            pad_token_id=1,
            hidden_size=16,
            intermediate_size=32,
            num_attention_heads=2,
            num_hidden_layers=1,
            vocab_size=100,
            max_position_embeddings=77,
            projection_dim=16,
        )
    )
    tok_dir = root / "tok"
    tok_dir.mkdir()
    chars = "abcdefghijklmnopqrstuvwxyz0123456789"
    vocab = {"<|startoftext|>": 0, "<|endoftext|>": 1}
    for c in chars:
        vocab[c] = len(vocab)
        vocab[c + "</w>"] = len(vocab)
    (tok_dir / "vocab.json").write_text(json.dumps(vocab))
    (tok_dir / "merges.txt").write_text("#version: 0.2\n")
    tokenizer = CLIPTokenizer.from_pretrained(str(tok_dir), model_max_length=77)  # as the real one
    sched = DDIMScheduler(
        beta_schedule="scaled_linear", beta_start=0.00085, beta_end=0.012, clip_sample=False, set_alpha_to_one=False
    )
    pipe = StableDiffusionPipeline(
        vae=vae,
        text_encoder=text,
        tokenizer=tokenizer,
        unet=unet,
        scheduler=sched,
        safety_checker=None,
        feature_extractor=None,
        requires_safety_checker=False,
    )
    pipe.save_pretrained(str(root / "sd"))
    ControlNetModel.from_unet(unet, conditioning_embedding_out_channels=(4, 4, 4, 4)).save_pretrained(str(root / "cn"))
    return root / "sd", root / "cn"


@pytest.fixture(scope="module")
def tiny_sd(tmp_path_factory):
    return build_tiny_sd(tmp_path_factory.mktemp("sd"))


def test_missing_weight_folder_names_the_files(tmp_path):
    with pytest.raises(InputError, match="model_index.json.*download"):
        cl.check_folders(tmp_path / "nope", tmp_path / "cn")


def test_one_lora_step_changes_only_lora_weights(tiny_sd):
    pipe = cl.load_pipeline(*tiny_sd, torch.device("cpu"))
    params = cl.add_lora(pipe, rank=4)
    assert params and all(p.requires_grad for p in params)
    named = {
        f"{m}.{n}": p.detach().clone()
        for m, mod in (("unet", pipe.unet), ("cn", pipe.controlnet), ("vae", pipe.vae), ("text", pipe.text_encoder))
        for n, p in mod.named_parameters()
    }
    # LoRA B starts at zero (a no-op); give it values so the step moves both A and B
    with torch.no_grad():
        for p in params:
            p.normal_(0, 0.1)
    named = {k: (v if "lora" not in k else None) for k, v in named.items()}
    lora_before = [p.detach().clone() for p in params]
    opt = torch.optim.Adam(params, lr=1e-2)
    g = torch.Generator().manual_seed(0)
    clean, bad = torch.rand(2, 3, 32, 32, generator=g), torch.rand(2, 3, 32, 32, generator=g)
    loss = cl.lora_step(pipe, params, opt, clean, bad, g)
    assert loss == loss  # not NaN
    assert any(not torch.equal(p.detach(), lora_before[i]) for i, p in enumerate(params))  # LoRA moved
    for m, mod in (("unet", pipe.unet), ("cn", pipe.controlnet), ("vae", pipe.vae), ("text", pipe.text_encoder)):
        for n, p in mod.named_parameters():
            before = named[f"{m}.{n}"]
            if before is not None:
                assert torch.equal(p.detach(), before), f"{m}.{n} changed"


def test_save_and_reload_reproduce_the_output(tiny_sd, tmp_path):
    pipe = cl.load_pipeline(*tiny_sd, torch.device("cpu"))
    params = cl.add_lora(pipe, rank=4)
    with torch.no_grad():
        for p in params:
            p.normal_(0, 0.1)
    x = torch.rand(1, 3, 32, 32, generator=torch.Generator().manual_seed(1))
    out1 = cl.repair(pipe, x, strength=0.5, steps=4, seed=3)
    cl.save_lora(tmp_path / "D_lora", pipe, {"sd_model": str(tiny_sd[0]), "controlnet": str(tiny_sd[1]), "rank": 4})
    pipe2, cfg = cl.load_lora(tmp_path / "D_lora", torch.device("cpu"))
    out2 = cl.repair(pipe2, x, strength=0.5, steps=4, seed=3)
    assert out1.shape == (1, 3, 32, 32) and torch.isfinite(out1).all()
    torch.testing.assert_close(out1, out2)
    assert cfg["prompt"] == cl.PROMPT


def test_finetune_and_repair_stages_with_controlnet(tiny_sd, tmp_path):
    """`wgs finetune --diffusion controlnet` trains LoRA on the LL pairs; `wgs repair` then uses it."""
    from click.testing import CliRunner
    from conftest import TINY

    from wgs.cli import cli
    from wgs.workspace import Workspace

    scene = make_scene(tmp_path / "scene", seed=6, size=48, n_train=4, n_test=2)
    cfg = tmp_path / "wgs.toml"
    cfg.write_text(TINY.replace("[finetune]", "[finetune]\nlora_steps = 2\nlora_rank = 4"))
    ws = tmp_path / "ws"

    def run(*args):
        res = CliRunner().invoke(cli, ["-q", "--config", str(cfg), "-w", str(ws), *args], catch_exceptions=False)
        assert res.exit_code == 0, res.output

    run("prepare", str(scene))
    run("coarse")
    run("mask-data")
    run("finetune", "--diffusion", "controlnet", "--sd-model", str(tiny_sd[0]), "--controlnet", str(tiny_sd[1]))
    w = Workspace(ws)
    assert (w.stage_dir("finetune") / "D_lora" / "lora.safetensors").is_file()
    assert (w.stage_dir("finetune") / "U" / "model.safetensors").is_file() == w.manifest("finetune")["u_used"]
    run("repair")
    views = json.loads((w.stage_dir("repair") / "views.json").read_text())
    assert views["views"] and (w.stage_dir("repair") / "pseudo" / views["views"][0]["name"]).is_file()


def test_controlnet_without_folders_is_a_clear_error(tmp_path):
    from wgs.stages.finetune.run import train_lora
    from wgs.stages.finetune.settings import FinetuneConfig

    with pytest.raises(InputError, match="--sd-model"):
        train_lora(None, FinetuneConfig(diffusion="controlnet"), None, None, torch.device("cpu"), None)
