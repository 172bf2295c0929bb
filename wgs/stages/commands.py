"""Click commands of the training stages (kept apart from cli.py so heavy imports stay lazy)."""

from __future__ import annotations

import click


def register(cli, stage_common, workspace_option) -> None:
    """Add the stage subcommands to the `wgs` group."""

    @cli.command()
    @click.option("--iterations", type=int, default=None, help="Training iterations.")
    @click.option("--max-seconds", type=float, default=None, help="Stop training after this many seconds.")
    @click.option("--sh-degree", type=int, default=None, help="Spherical-harmonics degree (0-3).")
    @stage_common
    @click.pass_obj
    def coarse(obj, iterations, max_seconds, sh_degree, force, preset):
        """Train the coarse 3DGS G_c on the training views."""
        from .s1_coarse import run_coarse

        cfg = obj.config("coarse", preset, iterations=iterations, max_seconds=max_seconds, sh_degree=sh_degree)
        if not 0 <= cfg.sh_degree <= 3:
            raise click.BadParameter(f"SH degree must be 0..3, got {cfg.sh_degree}", param_hint="--sh-degree")
        run_coarse(obj.ws(), cfg, obj.torch_device(), obj.seed, force=force)

    @cli.command("mask-data")
    @click.option("--strategy", type=click.Choice(["orm", "offline-rm", "loo"]), default=None,
                  help="orm: online random masking (default); offline-rm: static masks; loo: leave-one-out.")
    @click.option("--iterations", type=int, default=None, help="Training iterations (per model for loo).")
    @click.option("--n-regions", type=int, default=None, help="Mask regions per view (default 10).")
    @click.option("--coverage", type=float, default=None, help="Hidden fraction of the object area (default 0.5).")
    @stage_common
    @click.pass_obj
    def mask_data(obj, strategy, iterations, n_regions, coverage, force, preset):
        """Corrupted/clean pairs for the repair models (trains G_d, or N models for loo)."""
        from .s2_mask_data import run_mask_data

        cfg = obj.config("mask_data", preset, strategy=strategy, iterations=iterations, n_regions=n_regions,
                         coverage=coverage)
        run_mask_data(obj.ws(), cfg, obj.torch_device(), obj.seed, force=force)

    @cli.command()
    @click.option("--domain", type=click.Choice(["wavelet", "rgb"]), default=None,
                  help="wavelet: D repairs the LL subband and U the HF ones (default); rgb: D on RGB, no U.")
    @click.option("--no-u", "no_u", is_flag=True, default=None, help="Do not train the HF U-Net.")
    @click.option("--d-steps", type=int, default=None, help="Training steps of D.")
    @click.option("--u-max-steps", type=int, default=None, help="Step limit of U (early stopping ends it sooner).")
    @stage_common
    @click.pass_obj
    def finetune(obj, domain, no_u, d_steps, u_max_steps, force, preset):
        """Train the repair diffusion model D and the HF U-Net U."""
        from .s3_finetune import run_finetune

        cfg = obj.config("finetune", preset, domain=domain, use_u=False if no_u else None, d_steps=d_steps,
                         u_max_steps=u_max_steps)
        run_finetune(obj.ws(), cfg, obj.torch_device(), obj.seed, force=force)

    @cli.command()
    @click.option("--stage", "stage", type=click.Choice(["coarse"]), default="coarse", help="Which model.")
    @click.option("--views", type=click.Choice(["test", "train", "path"]), default="test", help="Cameras to render.")
    @click.option("--frames", type=int, default=60, help="Number of frames for --views path.")
    @workspace_option
    @click.pass_obj
    def render(obj, stage, views, frames):
        """Render a trained model to PNGs under WS/renders/STAGE_VIEWS/."""
        from .render_views import run_render

        run_render(obj.ws(), stage, views, frames, obj.torch_device())
