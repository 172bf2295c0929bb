"""Click options derived from the config dataclasses.

An option's type, its choices or range, and the "(default X)" in its help come from `wgs.config`
(the field's type, `CHOICES`, `RANGES`, the dataclass default); what the option means to a user
is written once here, in `MEANING`, and shared by every command that offers it (a stage's own
command and `wgs all`). Every option's click default is None: the config resolves
defaults < preset < file < CLI.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import Any

import click

from .config import CHOICES, CPU_TARGET_S, GPU_MAX_SIZE, PRESETS, RANGES, STAGES, field_types

# what each offered field means, in the words of the command line
MEANING: dict[str, str] = {
    # prepare
    "views": "Number of training views, spread over the viewing directions or from sparse_N.txt "
             "(not given: every training view of the dataset).",
    "downscale": "Integer image downscale factor (uses images_K/ if present; not given: the working size "
                 "chosen for the machine, see --max-size).",
    "max_size": "Downscale the photos by the smallest integer factor that brings their long side to at most this "
                f"many pixels (not given: {GPU_MAX_SIZE} on a GPU, on a CPU the largest size at which wgs all is "
                f"modelled to take about {CPU_TARGET_S / 60:.0f} minutes there).",
    "max_pixels": "Refuse images larger than this many pixels.",
    "matcher": "Photos without poses: feature matching for structure-from-motion "
               "(auto: exhaustive up to 150 photos, else sequential by name).",
    "masks": "Object masks: auto makes them where the scene has none (salient-object network + agreement "
             "between the posed views), none makes none, or a folder of masks named like the images.",
    "mask_agreement": "auto masks: share of the other views that must hold a voxel for it to stay object.",
    "mask_voter_support": "auto masks: a view votes only while the other voters hold this share of its mask.",
    "mask_colour_ratio": "auto masks: how much likelier on the mask than on the background a missed pixel's "
                         "colour must be to be put back (0: never).",
    "mask_max_missed": "auto masks: the most of a training mask that the training masks' hull may leave out.",
    "mask_max_cut": "auto masks: when agreement cuts more than this share of the network's object area, the "
                    "views disagree on the object and the scene goes on without masks (1: always keep them).",
    "mirror": "Where the object's leave-one-out silhouettes back a mirror plane, the training photos' mirror "
              "images join them as training views: outline teaches where the object is not (their masks carve; "
              "objects symmetric in shape), full their colours too (symmetric in shape and colour); none: no "
              "mirror views.",
    # 3DGS training (coarse, fine)
    "iterations": "Training iterations.",
    "max_seconds": "Stop training after this many seconds.",
    "sh_degree": "Spherical-harmonics degree.",
    "ensemble": "Coarse models from consecutive seeds; the repair averages their repaired renders (1: G_c alone).",
    # mask-data
    "strategy": "Pair generation: orm online random masking, offline-rm static masks, loo leave-one-out.",
    "n_regions": "Mask regions per view.",
    "coverage": "Hidden fraction of the object area.",
    # finetune
    "domain": "wavelet: D repairs the LL subband and U the HF ones; rgb: D on RGB, no U.",
    "use_u": "Train and use the HF U-Net U.",
    "levels": "Haar levels J (D at 1/2^J resolution).",
    "d_steps": "Training steps of D.",
    "diffusion": "embedded: our CPU-sized denoiser; controlnet: SD 1.5 + ControlNet-tile + LoRA.",
    "sd_model": "Local Stable Diffusion 1.5 folder.",
    "controlnet": "Local ControlNet-tile folder.",
    "u_max_steps": "Step limit of U (early stopping ends it sooner).",
    "prior_steps": "Fine-tune steps of the prior's D on this object's pairs (0: the prior as shipped).",
    "prior": "Start D and U from the pretrained repair prior (builtin), train them from scratch (none), "
             "or from a prior folder with D/ and U/.",
    # repair
    "poses": "Pseudo viewpoints: a band over the view sphere or arcs between training views.",
    "num_views": "Pseudo views in all (sphere poses).",
    "strength": "SDEdit strength (noise level) of a from-scratch D's repair (a prior's D runs one step).",
    "steps": "DDIM steps of a from-scratch D's repair.",
    "views_per_train": "Novel viewpoints per training view (arc poses).",
    "carve": "The volume model V and the silhouette model S carve the visual hull.",
    "shape_revolution": "Shrink the visual hull to the largest solid of revolution inside it where the photos' "
                        "masks allow it (bottles, vases, cups).",
    "shape_smooth": "Round off the visual hull's corners at the largest radius the photos' masks allow.",
    # fine
    "rounds": "Rounds of repair + refinement: each later one repairs the refined model's renders again.",
    "start": "Train G_f from the visual hull or from G_c (auto: the hull when the scene has masks).",
    "lpips_weights": "Folder with LPIPS weights (else $WGS_LPIPS_WEIGHTS, $TORCH_HOME/hub/checkpoints).",
    # eval
    "lpips_net": "LPIPS backbone.",
    "max_views": "Evaluate on the first N test views only.",
    "repair_gain_views": "Score the repair at N test poses spread over them (0: all).",
}

# flags whose names differ from their field: field -> click declaration
FLAG_NAMES: dict[str, str] = {"use_u": "--u/--no-u"}
# what a value looks like where its type says too little
METAVARS: dict[str, str] = {"prior": "builtin|none|DIR", "masks": "auto|none|DIR", "sd_model": "DIR",
                            "controlnet": "DIR", "lpips_weights": "DIR"}


def _shown(value: Any) -> str:
    return "none" if value is None else str(value).lower() if isinstance(value, bool) else str(value)


def option_type(name: str, tp: Any) -> click.ParamType:
    """The click type of a config field: its choices, its range, or its plain type."""
    if name in CHOICES:
        return click.Choice(CHOICES[name])
    if name in RANGES:
        low, high = RANGES[name]
        return click.IntRange(min=low, max=high) if tp is int else click.FloatRange(min=low, max=high)
    return {int: click.INT, float: click.FLOAT}.get(tp, click.STRING)


def config_option(table: str, name: str) -> Callable:
    """A click option for field `name` of stage table `table`'s config: `--name-with-dashes`
    (or `FLAG_NAMES`), typed, validated and with its default stated from the config."""
    cls = STAGES[table]
    tp = field_types(cls)[name]
    base = next((a for a in getattr(tp, "__args__", (tp,)) if a is not type(None)), tp)
    default = next(f.default for f in dataclasses.fields(cls) if f.name == name)
    text = MEANING[name]
    if default is not None:
        text = f"{text} (default {_shown(default)})"
    flag = "--" + name.replace("_", "-")
    if base is bool:
        decl = FLAG_NAMES.get(name, f"{flag}/--no-{flag[2:]}")
        return click.option(decl, name, default=None, help=text)
    return click.option(FLAG_NAMES.get(name, flag), name, type=option_type(name, base), default=None, help=text,
                        metavar=METAVARS.get(name))


def config_options(table: str, *names: str) -> Callable:
    """`config_option` for several fields of one table, listed in the help in the given order."""
    def apply(f: Callable) -> Callable:
        for name in reversed(names):
            f = config_option(table, name)(f)
        return f
    return apply


preset_option = click.option("--preset", type=click.Choice(list(PRESETS)), default=None, help="Budget preset.")
