"""Stage configurations: dataclasses with defaults, presets, a TOML file, and CLI overrides.

Precedence is CLI > config file > preset > dataclass defaults. A config file has one table per
stage (`[prepare]`, `[coarse]`, ...) plus optional top-level `device` and `seed`.
"""

from __future__ import annotations

import dataclasses
import types
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

try:
    import tomllib
except ModuleNotFoundError:  # Python 3.10
    import tomli as tomllib

from .errors import InputError
from .gaussians.strategy import DensifyParams
from .shape.carve import CarveParams
from .shape.own_shape import OwnShapeParams

# the working size chosen for the machine where neither downscale nor max_size is set (wgs.estimate)
GPU_MAX_SIZE = 1600  # px, a GPU's long side at most (the 3DGS convention)
CPU_TARGET_S = 600.0  # a CPU's: the largest size at which `wgs all` is modelled to take about this long


@dataclass
class PrepareConfig:
    views: int | None = None  # None: every training view of the dataset
    # the working size: photos downscaled by this integer factor; None: by the smallest factor that
    # brings their long side to max_size, and without max_size to the size chosen for the machine
    # (GPU_MAX_SIZE, CPU_TARGET_S)
    downscale: int | None = None
    max_size: int | None = None  # px, the working size's long side at most (with downscale unset)
    max_pixels: int = 4096 * 4096  # refuse larger images unless raised
    test_every: int = 8  # without a test split: every k-th non-training view
    # photos without poses: structure-from-motion (pycolmap)
    matcher: str = "auto"  # auto (exhaustive up to 150 photos, else sequential), exhaustive, sequential
    sfm_max_image_size: int = 1600  # SIFT on photos downscaled to this longest side
    # object masks: "auto" makes them where the scene has none (a salient-object network, then
    # agreement between the posed views, wgs.segment), "none" makes none, or a folder of masks by image name
    masks: str = "auto"
    mask_agreement: float = 0.85  # auto: a voxel stays object for a view when this share of the other views hold it
    # auto: a view's mask votes only while the other voters hold at least this share of it (a mask
    # of something else, the wall's pattern or half the object, would cut the object from the others)
    mask_voter_support: float = 0.7
    # auto: a pixel the network missed is put back where the voters' silhouette allows object and its
    # colour is this many times likelier on the mask than on the background (0: never)
    mask_colour_ratio: float = 10.0
    mask_model: str | None = None  # auto: an ONNX salient-object model to use instead of the packaged U^2-Net-p
    # auto: when agreement cuts more than this share of the network's object area (mean over the
    # views), the views disagree on what the object is, and the scene goes on without masks
    mask_max_cut: float = 0.3
    # auto: the training masks' strict hull may leave out at most this share of any training mask;
    # more means a mask misses part of the object, which the hull would then cut from every view
    mask_max_missed: float = 0.05
    # where the object's leave-one-out silhouettes back a mirror plane (wgs.shape.symmetry), the
    # training photos' mirror images join them as training views: "outline" teaches where the object
    # is not (their masks carve: objects symmetric in shape), "full" their colours too (symmetric in
    # shape and colour: the check sees masks only); "none": no mirror views
    mirror: str = "outline"
    mirror_min_gain: float = 0.02  # the mirror must raise the mean leave-one-out silhouette IoU by this
    # ... and the hull of the photos and their mirror images may miss at most this share of the
    # photos' masks (mean over the photos): a plane the object only roughly follows cuts it
    mirror_max_missed: float = 0.02
    mirror_directions: int = 400  # plane normals tried, spread over a hemisphere


@dataclass
class TrainConfig(DensifyParams):
    """The shared 3DGS training loop (coarse, mask-data, fine); densification fields and defaults
    come from `gaussians.strategy.DensifyParams`."""

    iterations: int = 2000
    max_seconds: float | None = None  # a time budget: schedules then follow the elapsed fraction of it
    sh_degree: int = 2
    sh_increase_every: int = 500
    lr_means: float = 1.6e-4  # times the scene extent
    lr_means_final: float = 1.6e-6
    lr_quats: float = 1e-3
    lr_scales: float = 5e-3
    lr_opacities: float = 5e-2
    lr_sh0: float = 2.5e-3
    lr_shN: float = 2.5e-3 / 20
    ssim_weight: float = 0.2
    mask_weight: float = 0.1
    # views that teach the outline only (mirror views): the weight of the opacity outside their mask
    # grown by this many pixels (the photos decide within that margin)
    outline_weight: float = 1.0
    outline_margin_px: int = 1
    # the views at half size (2x2 pixel means) for this fraction of the schedule: the early
    # iterations, which fit the coarse shape, cost about half as much
    half_size_until: float = 0.0
    random_background: bool = True
    init_points: int = 5000  # visual-hull points at most
    hull_resolution: int = 96
    floater_every: int = 500
    floater_k: int = 8
    floater_lambda: float = 3.0
    log_every: int = 50


def time_boxed(cfg: Any, seconds: float, planned_seconds: float, headroom: float) -> Any:
    """`cfg` (a TrainConfig) stopped after `seconds` of training: its iteration and densification
    caps scaled by the time over `planned_seconds` (what its own iterations take) times `headroom`,
    so that the time, not the caps, ends it; its schedules then follow the elapsed fraction."""
    scale = max(1.0, seconds / max(planned_seconds, 1e-6)) * headroom
    return dataclasses.replace(cfg, iterations=int(cfg.iterations * scale), refine_stop=int(cfg.refine_stop * scale),
                               max_seconds=seconds)


@dataclass
class CurveConfig:
    """Quality against time inside a training loop (curve.json): test PSNR / SSIM on a few fixed test
    views every so many training seconds (the probe's own time is left out of the clock)."""

    curve_every_s: float = 5.0  # 0: no curve
    curve_views: int = 4
    curve_points: int = 6  # and a probe at least every iterations / curve_points (short runs, fast machines)


@dataclass
class CoarseConfig(CurveConfig, TrainConfig):
    iterations: int = 1500
    # coarse models trained with seeds seed .. seed + ensemble - 1 (the first is G_c); the repair
    # averages their repaired renders: their sparse-view artifacts differ, the object does not
    # (docs/repair-prior.md)
    ensemble: int = 6
    half_size_until: float = 0.3


@dataclass
class MaskDataConfig(TrainConfig):
    """Training of G_d (or the N leave-one-out models) and the corrupted/clean pairs it yields."""

    iterations: int = 1500
    strategy: str = "orm"  # orm | offline-rm | loo
    n_regions: int = 10
    coverage: float = 0.5  # fraction of the object's mask area hidden at any time
    drift: float = 0.08  # sinusoidal displacement amplitude, fraction of the object's size
    drift_period: float = 400.0  # iterations
    warmup: int = 500  # no pairs before this iteration
    pair_every: int = 100
    half_size_until: float = 0.3


@dataclass
class FinetuneConfig:
    """The LL-domain repair diffusion model D and the HF U-Net U."""

    domain: str = "wavelet"  # wavelet: D on the LL subband + U on HF; rgb: D on RGB, no U
    levels: int = 1  # Haar levels J: D works at 1/2^J resolution
    diffusion: str = "embedded"  # embedded: our CPU-sized denoiser; controlnet: SD 1.5 + ControlNet + LoRA
    sd_model: str | None = None  # local Stable Diffusion 1.5 folder (controlnet)
    controlnet: str | None = None  # local ControlNet-tile folder (controlnet)
    lora_rank: int = 64
    lora_lr: float = 1e-3
    lora_steps: int = 500
    lora_crop: int = 64
    use_u: bool = True
    prior: str = "builtin"  # builtin: the prior shipped in wgs/prior/weights; none: from scratch; or a folder
    prior_steps: int = 150  # per-object fine-tune of the prior D (early-stopped on held-out pairs); 0: as shipped
    prior_lr: float = 5e-5
    prior_eval_every: int = 25
    prior_patience: int = 4
    train_timesteps: int = 1000
    d_channels: int = 32  # base width; the U-Net uses (c, 2c, 2c)
    d_steps: int = 1500
    d_batch: int = 16
    d_crop: int = 32
    d_lr: float = 2e-4
    ema_decay: float = 0.995
    u_channels: int = 16
    u_max_steps: int = 1500
    u_batch: int = 16
    u_crop: int = 32
    u_lr: float = 1e-3
    u_eval_every: int = 50
    u_patience: int = 5
    holdout: float = 0.15  # fraction of pairs kept out of training to measure D
    eval_strength: float = 0.5  # SDEdit strength of the held-out check
    eval_steps: int = 10


@dataclass
class RepairConfig(OwnShapeParams, CarveParams):
    """Pseudo references at novel poses, the visual hull shrunk by what the photos' masks allow
    (`shape.own_shape.OwnShapeParams`), and its carving by the volume model V and the silhouette
    model S (the thresholds come from `shape.carve.CarveParams`)."""

    poses: str = "sphere"  # sphere: a Fibonacci band over the view sphere; arc: between neighbouring training views
    num_views: int = 24  # sphere: pseudo views in all
    # sphere: the band's elevations, from band_below degrees under the lowest training camera to
    # band_above over the highest
    band_below: float = 15.0
    band_above: float = 40.0
    views_per_train: int = 2  # arc: novel viewpoints per training view (spread over neighbour pairs)
    arc_min: float = 0.3  # fraction of the arc between neighbouring training cameras
    arc_max: float = 0.7
    strength: float = 0.5  # SDEdit: noise level the corrupted image is taken to before denoising
    steps: int = 10  # DDIM steps
    # D repairs each render under this many flips / transposes of it (1..8), averaged; ensemble
    # members take different ones, so D's errors differ between them
    symmetries: int = 1
    # The visual hull (every mask agreeing) is carved where the volume model V is sure of background,
    # then where the silhouette model S is sure at the pseudo views; G_f starts from the carved hull
    # and learns opacity at the pseudo views inside its outline. Needs masks and V's or S's weights
    carve: bool = True
    silhouette_model: str = "builtin"  # builtin: wgs/prior/weights/S; or a folder holding S
    volume_model: str = "builtin"  # builtin: wgs/prior/weights/V; or a folder holding V
    hull_resolution: int = TrainConfig.hull_resolution  # voxels along the carved hull's box
    carve_views: int = 32  # S also predicts at this many views over the whole sphere, for carving only


@dataclass
class LpipsWeightsConfig:
    """Where LPIPS weights are looked for, the same for the fine stage's LPIPS term and eval."""

    lpips_weights: str | None = None  # folder; also $WGS_LPIPS_WEIGHTS, $TORCH_HOME/hub/checkpoints, lpips package


@dataclass
class FineConfig(LpipsWeightsConfig, CurveConfig, TrainConfig):
    """Refinement of G_c on the real and the pseudo references."""

    iterations: int = 1500
    refine_start: int = 100
    refine_stop: int = 1000
    half_size_until: float = 0.3  # real and pseudo views halved, as in the coarse stage
    # where G_f starts: "hull" trains afresh from the visual-hull init on the real and pseudo views
    # together (G_c's 4-view artifacts are not dragged along), "coarse" refines G_c, "auto" is hull
    # when the scene has masks (else there is no hull to start from)
    start: str = "auto"
    pseudo_weight_start: float = 1.0  # a pseudo view's weight against a real view's at the start
    pseudo_weight_end: float = 1.0  # reached at pseudo_until of the iterations; 0 after (real views only)
    pseudo_until: float = 1.0  # fraction of the iterations with pseudo views (GaussianObject: 0.7)
    pseudo_every: int = 2  # one pseudo-view step every k iterations
    lpips_weight: float = 0.1  # LPIPS (VGG) on the pseudo views, used when its weights are on this machine
    rounds: int = 1  # > 1: the pseudo views are rendered from the refined model, repaired again, trained again


@dataclass
class EvalConfig(LpipsWeightsConfig):
    lpips_net: str = "alex"  # alex | vgg
    max_views: int | None = None  # evaluate on the first k test views only
    repair_gain: bool = True  # also repair G_c's renders at the test poses and score them (the repair's own gain)
    # at this many test poses spread evenly over them (0: all): each repairs every member's render
    repair_gain_views: int = 25
    # the visual hull's grid (voxels along its box's side) whose silhouettes are scored at the test
    # views and, leaving each training view out in turn, at the training views
    hull_resolution: int = TrainConfig.hull_resolution
    turntable_frames: int = 48  # a GIF of the final model on an orbit fitted to the training cameras; 0: none


@dataclass
class BaselineConfig:
    """Plain 3DGS (the coarse stage's trainer and settings, one model, no repair) trained for the
    time the pipeline's training stages took: what that time buys without WaveletGaussian."""

    # iteration and densification caps, as a multiple of G_c's own rate over the budget: the time
    # budget, not the caps, ends the training
    headroom: float = 4.0


@dataclass
class AllConfig:
    """`wgs all` as a whole (the `[all]` table)."""

    # a time budget for the run, such as "10m", "90s" or "1h" (a bare number is minutes): the working
    # size and the training stages' time are chosen so that the run ends within it (wgs.estimate)
    budget: str | None = None


@dataclass(frozen=True)
class Stage:
    """One stage of the pipeline, the one place its facts live: `name` keys the workspace (manifests,
    `Workspace.stage_dir`), `folder` is its folder in the workspace, `command` its `wgs` command,
    `config` its settings (the [table] named like the command, '-' as '_'), `upstream` the stages
    whose outputs it reads (their fingerprints make it stale), `runner` its run function
    (`module:function` in wgs.stages, see `stages.run_stage`), `outputs` what it writes for others
    to read (key -> path in its folder; readers ask `Workspace.output(stage, key)`), `method` False
    for what only measures, `on_request` True for what runs only when asked for."""

    name: str
    folder: str
    command: str
    config: type
    upstream: tuple[str, ...]
    runner: str
    outputs: dict[str, str] = field(default_factory=dict)
    method: bool = True
    on_request: bool = False

    @property
    def table(self) -> str:
        return self.command.replace("-", "_")


_MODEL = {"model": "ckpt.pt",  # the model (normalised world) and its iteration
          "ply": "point_cloud.ply",  # the model in the INRIA layout, world coordinates
          "curve": "curve.json"}  # test PSNR / SSIM on probe views against training time (curves.py)

REGISTRY: tuple[Stage, ...] = (
    Stage("scene", "scene", "prepare", PrepareConfig, (), "s0_prepare:run_prepare",
          {"prepared": ".", "info": "scene.json",
           "masks_sheet": "masks_sheet.png",  # automatic masks: the training photos with their outline
           "masks_proposed": "masks_proposed"}),  # automatic masks not used (auto_failed): to correct
    Stage("coarse", "1_coarse", "coarse", CoarseConfig, ("scene",), "s1_coarse:run_coarse",
          {**_MODEL, "members": "members",  # the ensemble's other models, members/ckpt_<i>.pt (i >= 1)
           "subbands": "subbands"}),  # Haar subbands of the training views, subbands/{ref,render}/<stem>.exr
    Stage("mask_data", "2_mask_data", "mask-data", MaskDataConfig, ("scene", "coarse"), "s2_mask_data:run_mask_data",
          {"index": "index.json"}),  # the corrupted / clean pairs, paths relative to it
    Stage("finetune", "3_finetune", "finetune", FinetuneConfig, ("coarse", "mask_data"), "s3_finetune:run_finetune",
          {"models": "."}),  # D/ (or D_lora/) and U/
    Stage("repair", "4_repair", "repair", RepairConfig, ("scene", "coarse", "finetune"), "s4_repair:run_repair",
          {"views": "views.json",  # the pseudo views' cameras and weights (and S's silhouette files)
           "silhouettes": "silhouettes",  # per pseudo view, where the object may be (black: S is sure of background)
           "carved_hull": "carved_hull.npz",  # the visual hull carved by V and S (shape.hull.save_grid)
           "pseudo": "pseudo",  # the pseudo references, <stem>.exr (RGB, float) and <name> (PNG)
           "contact_sheet": "contact_sheet.png"}),
    # fine rounds run the repair again, so it reads finetune's models too
    Stage("fine", "5_fine", "fine", FineConfig, ("scene", "coarse", "finetune", "repair"), "s5_fine:run_fine",
          dict(_MODEL)),
    Stage("baseline", "baseline", "baseline", BaselineConfig, ("scene", "coarse", "fine"), "baseline:run_baseline",
          {"model": _MODEL["model"], "curve": _MODEL["curve"]}, method=False, on_request=True),
    Stage("eval", "6_eval", "eval", EvalConfig, ("scene", "coarse", "repair", "fine", "baseline"), "s6_eval:run_eval",
          {"results": "results.json", "report": "report.md", "report_html": "report.html"}, method=False),
)
STAGES: dict[str, type] = {s.table: s.config for s in REGISTRY}  # config table -> settings class
TABLE_OF: dict[str, str] = {s.name: s.table for s in REGISTRY}  # stage name -> its config table
STAGE_OF_TABLE: dict[str, str] = {s.table: s.name for s in REGISTRY}  # config table -> stage name
METHOD: tuple[str, ...] = tuple(s.name for s in REGISTRY if s.method)  # what a reconstruction runs, in order
OUTPUTS: dict[str, dict[str, str]] = {s.name: s.outputs for s in REGISTRY}
UNASKED: tuple[str, ...] = tuple(s.name for s in REGISTRY if not s.on_request)  # what `wgs all` runs unasked
RUN_TABLES: dict[str, type] = {"all": AllConfig}  # config-file tables of a whole run, beside the stages'


def stages_through(name: str) -> tuple[str, ...]:
    """The method's stages up to and including `name`."""
    return METHOD[: METHOD.index(name) + 1]


# Small budgets for the bundled example (`make demo`), shared by every 3DGS training stage.
# a few hundred iterations leave no room for a half-size phase (docs/speed.md)
_FAST_TRAIN = {"refine_start": 100, "refine_every": 50, "sh_degree": 1, "sh_increase_every": 200,
               "init_points": 3000, "hull_resolution": 64, "max_gaussians": 20000, "floater_every": 200,
               "half_size_until": 0.0}

PRESETS: dict[str, dict[str, dict[str, Any]]] = {
    "fast": {
        "coarse": {**_FAST_TRAIN, "iterations": 400, "refine_stop": 300, "ensemble": 1},
        "mask_data": {**_FAST_TRAIN, "iterations": 200, "refine_stop": 150, "warmup": 60, "pair_every": 28,
                      "drift_period": 100.0},
        "finetune": {"d_steps": 300, "u_max_steps": 100, "d_channels": 16, "u_eval_every": 25, "u_patience": 2,
                     "prior_steps": 15},
        "repair": {"steps": 5, "num_views": 16, "band_above": 25.0},
        "fine": {**_FAST_TRAIN, "iterations": 300, "refine_start": 50, "refine_stop": 200},
    },
    "default": {},
    "paper": {
        "coarse": {"iterations": 10000, "refine_stop": 7000, "sh_degree": 3, "max_gaussians": 1000000,
                   "init_points": 100000, "hull_resolution": 128, "reset_every": 3000},
    },
}

GLOBAL_KEYS = {"device": str, "seed": int, "preset": str}


def _accepts(tp: Any, value: Any) -> bool:
    origin = typing.get_origin(tp)
    if origin in (typing.Union, types.UnionType):
        return any(_accepts(a, value) for a in typing.get_args(tp))
    if tp is type(None):
        return value is None
    if tp is float:
        return isinstance(value, int | float) and not isinstance(value, bool)
    if tp is int:
        return isinstance(value, int) and not isinstance(value, bool)
    return isinstance(value, tp)


def field_types(cls: type) -> dict[str, Any]:
    hints = typing.get_type_hints(cls)
    return {f.name: hints[f.name] for f in dataclasses.fields(cls)}


def check_table(cls: type, table: dict[str, Any], where: str, path: str | Path | None = None) -> None:
    """Raise InputError naming the first unknown key or wrongly typed value."""
    types_ = field_types(cls)
    for key, value in table.items():
        if key not in types_:
            raise InputError(f"unknown key '{where}.{key}' (known: {', '.join(sorted(types_))})", path)
        if not _accepts(types_[key], value):
            raise InputError(f"key '{where}.{key}' must be {types_[key]}, got {value!r}", path)


def load_config_file(path: str | Path) -> dict[str, Any]:
    """Read and validate a wgs.toml; returns {'global': {...}, stage: {...}}."""
    path = Path(path)
    try:
        with open(path, "rb") as fh:
            data = tomllib.load(fh)
    except FileNotFoundError:
        raise InputError("config file not found", path) from None
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise InputError(f"not valid TOML: {exc}", path) from None
    out: dict[str, Any] = {"global": {}}
    for key, value in data.items():
        if isinstance(value, dict):
            name = key.replace("-", "_")
            tables = {**STAGES, **RUN_TABLES}
            if name not in tables:
                raise InputError(f"unknown table '[{key}]' (known: {', '.join(tables)})", path)
            check_table(tables[name], value, key, path)
            out[name] = value
        elif key in GLOBAL_KEYS:
            if not isinstance(value, GLOBAL_KEYS[key]) or isinstance(value, bool):
                raise InputError(f"key '{key}' must be {GLOBAL_KEYS[key].__name__}, got {value!r}", path)
            out["global"][key] = value
        else:
            raise InputError(f"unknown key '{key}'", path)
    return out


def resolve(stage: str, preset: str | None = None, file_cfg: dict[str, Any] | None = None,
            cli: dict[str, Any] | None = None) -> Any:
    """Build a stage's config: defaults < preset < file < CLI (CLI values of None are ignored)."""
    cls = STAGES[stage]
    values: dict[str, Any] = {}
    if preset is not None:
        if preset not in PRESETS:
            raise InputError(f"unknown preset {preset!r} (known: {', '.join(PRESETS)})")
        values.update(PRESETS[preset].get(stage, {}))
    values.update((file_cfg or {}).get(stage, {}))
    values.update({k: v for k, v in (cli or {}).items() if v is not None})
    check_table(cls, values, stage)
    cfg = cls(**values)
    check_choices(cfg)
    return cfg


def as_dict(cfg: Any) -> dict[str, Any]:
    return dataclasses.asdict(cfg)


# the allowed values of a text field, whichever stage's config holds it
CHOICES: dict[str, tuple[str, ...]] = {"strategy": ("orm", "offline-rm", "loo"), "domain": ("wavelet", "rgb"),
                                       "poses": ("sphere", "arc"), "start": ("auto", "coarse", "hull"),
                                       "lpips_net": ("alex", "vgg"), "diffusion": ("embedded", "controlnet"),
                                       "matcher": ("auto", "exhaustive", "sequential"),
                                       "mirror": ("none", "outline", "full")}


# the allowed range of a numeric field, inclusive (None: open), whichever stage's config holds it
RANGES: dict[str, tuple[float, float | None]] = {"views": (2, None), "downscale": (1, None), "max_size": (16, None),
                                                 "sh_degree": (0, 3),
                                                 "ensemble": (1, None), "symmetries": (1, 8),
                                                 "repair_gain_views": (0, None), "mask_agreement": (0.0, 1.0),
                                                 "mask_voter_support": (0.0, 1.0), "mask_max_missed": (0.0, 1.0),
                                                 "mask_colour_ratio": (0.0, None),
                                                 "mask_max_cut": (0.0, 1.0), "mirror_directions": (1, None),
                                                 "mirror_max_missed": (0.0, 1.0), "outline_margin_px": (0, None),
                                                 "shape_max_missed": (0.0, 1.0),
                                                 "half_size_until": (0.0, 1.0), "prior_steps": (0, None)}


def check_choices(cfg: Any) -> None:
    for key, allowed in CHOICES.items():
        v = getattr(cfg, key, None)
        if v is not None and v not in allowed:
            raise InputError(f"'{key}' must be one of {', '.join(allowed)}, got {v!r}")
    for key, (low, high) in RANGES.items():
        v = getattr(cfg, key, None)
        if v is not None and v < low:
            raise InputError(f"'{key}' must be at least {low}, got {v!r}")
        if v is not None and high is not None and v > high:
            raise InputError(f"'{key}' must be at most {high}, got {v!r}")
