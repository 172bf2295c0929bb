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
    import tomli as tomllib  # type: ignore[no-redef]

from .errors import InputError
from .fields import facts, option
from .gaussians.stopping import StopParams
from .gaussians.trainer import TrainConfig
from .segment.accept import MaskParams
from .shape.carve import CarveParams
from .shape.own_shape import OwnShapeParams

# the working size chosen for the machine where neither downscale nor max_size is set (wgs.estimate)
GPU_MAX_SIZE = 1600  # px, a GPU's long side at most (the 3DGS convention)
CPU_TARGET_S = 600.0  # a CPU's: the largest size at which `wgs all` is modelled to take about this long


@dataclass
class PrepareConfig(MaskParams):
    """The import of a scene; the automatic masks' fields come from `segment.accept.MaskParams`."""

    views: int | None = option(
        None,
        "Number of training views, spread over the viewing directions or from sparse_N.txt (not given: every "
        "training view of the dataset).",
        bounds=(2, None),
    )
    # the working size: photos downscaled by this integer factor; None: by the smallest factor that
    # brings their long side to max_size, and without max_size to the size chosen for the machine
    # (GPU_MAX_SIZE, CPU_TARGET_S)
    downscale: int | None = option(
        None,
        "Integer image downscale factor (uses images_K/ if present; not given: the working size chosen for the "
        "machine, see --max-size).",
        bounds=(1, None),
    )
    max_size: int | None = option(
        None,
        (
            "Downscale the photos by the smallest integer factor that brings their long side to at most this "
            f"many pixels (not given: {GPU_MAX_SIZE} on a GPU, on a CPU the largest size at which wgs all is "
            f"modelled to take about {CPU_TARGET_S / 60:.0f} minutes there)."
        ),
        bounds=(16, None),
    )
    max_pixels: int = option(4096 * 4096, "Refuse images larger than this many pixels.")
    test_every: int = 8  # without a test split: every k-th non-training view
    # photos without poses: structure-from-motion (pycolmap)
    matcher: str = option(
        "auto",
        "Photos without poses: feature matching for structure-from-motion (auto: learned matching for a few "
        "photos, or where SIFT registers too few of a small set; SIFT exhaustive up to 150 photos, else sequential "
        "by name).",
        choices=("auto", "learned", "exhaustive", "sequential"),
    )
    focal: float | None = option(
        None,
        "Photos without poses: their focal length in pixels at full size, where known (else EXIF, else refined).",
        bounds=(1, None),
    )
    fov: float | None = option(
        None,
        "Photos without poses: their horizontal field of view in degrees, where known (instead of --focal).",
        bounds=(1, 179),
    )
    sfm_max_image_size: int = 1600  # SIFT on photos downscaled to this longest side
    # photos wgs posed from a few views (learned matching), with masks of their own: the cameras
    # corrected by training one coarse model on the photos (wgs.gaussians.pose_refine), and
    # kept unless the hull of the other photos then leaves out more of each photo's mask
    cameras: str = option(
        "correct",
        "Photos wgs posed from a few views: correct trains their cameras with a model and keeps the correction "
        "unless the photos' masks then agree worse; posed keeps the cameras as structure-from-motion placed them.",
        choices=("correct", "posed"),
    )
    camera_iterations: int = option(1500, bounds=(1, None))  # the correcting model's iterations
    camera_lr: float = 1e-4  # Adam's step for each camera's rotation (radians) and shift (normalised units)
    # object masks: "auto" makes them where the scene has none (a salient-object network, then
    # agreement between the posed views, wgs.segment), "none" makes none, or a folder of masks by image name
    masks: str = option(
        "auto",
        "Object masks: auto makes them where the scene has none (salient-object network + agreement between the "
        "posed views), none makes none, or a folder of masks named like the images.",
        metavar="auto|none|DIR",
    )
    # where the object's leave-one-out silhouettes back a mirror plane (wgs.shape.symmetry), the
    # training photos' mirror images join them as training views: "outline" teaches where the object
    # is not (their masks carve: objects symmetric in shape), "full" their colours too (symmetric in
    # shape and colour: the check sees masks only); "none": no mirror views
    mirror: str = option(
        "outline",
        "Where the object's leave-one-out silhouettes back a mirror plane, the training photos' mirror images join "
        "them as training views: outline teaches where the object is not (their masks carve; objects symmetric in "
        "shape), full their colours too (symmetric in shape and colour); none: no mirror views.",
        choices=("none", "outline", "full"),
    )
    mirror_min_gain: float = 0.02  # the mirror must raise the mean leave-one-out silhouette IoU by this
    # ... and the hull of the photos and their mirror images may miss at most this share of the
    # photos' masks (mean over the photos): a plane the object only roughly follows cuts it
    mirror_max_missed: float = option(0.02, bounds=(0.0, 1.0))
    mirror_directions: int = option(400, bounds=(1, None))  # plane normals tried, spread over a hemisphere


def time_boxed(cfg: Any, seconds: float, planned_seconds: float, headroom: float) -> Any:
    """`cfg` (a TrainConfig) stopped after `seconds` of training: its iteration and densification
    caps scaled by the time over `planned_seconds` (what its own iterations take) times `headroom`,
    so that the time, not the caps, ends it; its schedules then follow the elapsed fraction."""
    scale = max(1.0, seconds / max(planned_seconds, 1e-6)) * headroom
    return dataclasses.replace(
        cfg, iterations=int(cfg.iterations * scale), refine_stop=int(cfg.refine_stop * scale), max_seconds=seconds
    )


@dataclass
class CurveConfig:
    """Quality against time inside a training loop (curve.json): test PSNR / SSIM on a few fixed test
    views every so many training seconds (the probe's own time is left out of the clock)."""

    curve_every_s: float = 5.0  # 0: no curve
    curve_views: int = 4
    curve_points: int = 6  # and a probe at least every iterations / curve_points (short runs, fast machines)


@dataclass
class CoarseConfig(CurveConfig, StopParams, TrainConfig):
    iterations: int = 1500
    # coarse models trained with seeds seed .. seed + ensemble - 1 (the first is G_c); the repair
    # averages their repaired renders: their sparse-view artifacts differ, the object does not
    # (docs/repair-prior.md)
    ensemble: int = option(
        6,
        "Coarse models from consecutive seeds; the repair averages their repaired renders (1: G_c alone).",
        bounds=(1, None),
    )
    half_size_until: float = 0.3


@dataclass
class MaskDataConfig(TrainConfig):
    """Training of G_d (or the N leave-one-out models) and the corrupted/clean pairs it yields."""

    iterations: int = 1500
    strategy: str = option(
        "orm",
        "Pair generation: orm online random masking, offline-rm static masks, loo leave-one-out.",
        choices=("orm", "offline-rm", "loo"),
    )
    n_regions: int = option(10, "Mask regions per view.")
    coverage: float = option(0.5, "Hidden fraction of the object area.")
    drift: float = 0.08  # sinusoidal displacement amplitude, fraction of the object's size
    drift_period: float = 400.0  # iterations
    warmup: int = 500  # no pairs before this iteration
    pair_every: int = 100
    half_size_until: float = 0.3


@dataclass
class FinetuneConfig:
    """The LL-domain repair diffusion model D and the HF U-Net U."""

    domain: str = option(
        "wavelet",
        "wavelet: D repairs the LL subband and U the HF ones; rgb: D on RGB, no U.",
        choices=("wavelet", "rgb"),
    )
    levels: int = option(1, "Haar levels J (D at 1/2^J resolution).")
    diffusion: str = option(
        "embedded",
        "embedded: our CPU-sized denoiser; controlnet: SD 1.5 + ControlNet-tile + LoRA.",
        choices=("embedded", "controlnet"),
    )
    sd_model: str | None = option(None, "Local Stable Diffusion 1.5 folder.", metavar="DIR")
    controlnet: str | None = option(None, "Local ControlNet-tile folder.", metavar="DIR")
    lora_rank: int = 64
    lora_lr: float = 1e-3
    lora_steps: int = 500
    lora_crop: int = 64
    use_u: bool = option(True, "Train and use the HF U-Net U.", flags=("--u/--no-u",))
    prior: str = option(
        "builtin",
        "Start D and U from the pretrained repair prior (builtin), train them from scratch (none), or from a prior "
        "folder with D/ and U/.",
        metavar="builtin|none|DIR",
    )
    prior_steps: int = option(
        150, "Fine-tune steps of the prior's D on this object's pairs (0: the prior as shipped).", bounds=(0, None)
    )
    prior_lr: float = 5e-5
    prior_eval_every: int = 25
    prior_patience: int = 4
    train_timesteps: int = 1000
    d_channels: int = 32  # base width; the U-Net uses (c, 2c, 2c)
    d_steps: int = option(1500, "Training steps of D.")
    d_batch: int = 16
    d_crop: int = 32
    d_lr: float = 2e-4
    ema_decay: float = 0.995
    u_channels: int = 16
    u_max_steps: int = option(1500, "Step limit of U (early stopping ends it sooner).")
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

    poses: str = option(
        "sphere",
        "Pseudo viewpoints: a band over the view sphere or arcs between training views.",
        choices=("sphere", "arc"),
    )
    num_views: int = option(24, "Pseudo views in all (sphere poses).")
    # sphere: the band's elevations, from band_below degrees under the lowest training camera to
    # band_above over the highest
    band_below: float = 15.0
    band_above: float = 40.0
    views_per_train: int = option(2, "Novel viewpoints per training view (arc poses).")
    arc_min: float = 0.3  # fraction of the arc between neighbouring training cameras
    arc_max: float = 0.7
    strength: float = option(
        0.5, "SDEdit strength (noise level) of a from-scratch D's repair (a prior's D runs one step)."
    )
    steps: int = option(10, "DDIM steps of a from-scratch D's repair.")
    # D repairs each render under this many flips / transposes of it (1..8), averaged; ensemble
    # members take different ones, so D's errors differ between them
    symmetries: int = option(1, bounds=(1, 8))
    # The visual hull (every mask agreeing) is carved where the volume model V is sure of background,
    # then where the silhouette model S is sure at the pseudo views; G_f starts from the carved hull
    # and learns opacity at the pseudo views inside its outline. Needs masks and V's or S's weights
    carve: bool = option(True, "The volume model V and the silhouette model S carve the visual hull.")
    silhouette_model: str = "builtin"  # builtin: wgs/weights/S; or a folder holding S
    volume_model: str = "builtin"  # builtin: wgs/weights/V; or a folder holding V
    hull_resolution: int = TrainConfig.hull_resolution  # voxels along the carved hull's box
    carve_views: int = 32  # S also predicts at this many views over the whole sphere, for carving only


@dataclass
class LpipsWeightsConfig:
    """Where LPIPS weights are looked for, the same for the fine stage's LPIPS term and eval."""

    lpips_weights: str | None = option(
        None, "Folder with LPIPS weights (else $WGS_LPIPS_WEIGHTS, $TORCH_HOME/hub/checkpoints).", metavar="DIR"
    )


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
    start: str = option(
        "auto",
        "Train G_f from the visual hull or from G_c (auto: the hull when the scene has masks).",
        choices=("auto", "coarse", "hull"),
    )
    pseudo_weight_start: float = 1.0  # a pseudo view's weight against a real view's at the start
    pseudo_weight_end: float = 1.0  # reached at pseudo_until of the iterations; 0 after (real views only)
    pseudo_until: float = 1.0  # fraction of the iterations with pseudo views (GaussianObject: 0.7)
    pseudo_every: int = 2  # one pseudo-view step every k iterations
    lpips_weight: float = 0.1  # LPIPS (VGG) on the pseudo views, used when its weights are on this machine
    rounds: int = option(1, "Rounds of repair + refinement: each later one repairs the refined model's renders again.")


@dataclass
class EvalConfig(LpipsWeightsConfig):
    lpips_net: str = option("alex", "LPIPS backbone.", choices=("alex", "vgg"))
    max_views: int | None = option(None, "Evaluate on the first N test views only.")
    repair_gain: bool = True  # also repair G_c's renders at the test poses and score them (the repair's own gain)
    # at this many test poses spread evenly over them (0: all): each repairs every member's render
    repair_gain_views: int = option(25, "Score the repair at N test poses spread over them (0: all).", bounds=(0, None))
    # the visual hull's grid (voxels along its box's side) whose silhouettes are scored at the test
    # views and, leaving each training view out in turn, at the training views
    hull_resolution: int = TrainConfig.hull_resolution
    localise_steps: int = option(
        60,
        "Photos posed by wgs: move each test camera this many steps to where the final model fits its photo best, "
        "and score there, as pose-free methods do (0: score at the posed cameras).",
        bounds=(0, None),
    )
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

    budget: str | None = option(
        None,
        "A time budget for the run, such as 10m, 90s or 1h (a bare number is minutes; also [all] budget): the "
        "working size and the training stages' time are chosen to end within it.",
    )


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


_MODEL = {
    "model": "ckpt.pt",  # the model (normalised world) and its iteration
    "ply": "point_cloud.ply",  # the model in the INRIA layout, world coordinates
    "curve": "curve.json",
}  # test PSNR / SSIM on probe views against training time (curves.py)

REGISTRY: tuple[Stage, ...] = (
    Stage(
        "scene",
        "scene",
        "prepare",
        PrepareConfig,
        (),
        "s0_prepare:run_prepare",
        {
            "prepared": ".",
            "info": "scene.json",
            "masks_sheet": "masks_sheet.png",  # automatic masks: the training photos with their outline
            "masks_proposed": "masks_proposed",
        },
    ),  # automatic masks not used (auto_failed): to correct
    Stage(
        "coarse",
        "1_coarse",
        "coarse",
        CoarseConfig,
        ("scene",),
        "s1_coarse:run_coarse",
        {
            **_MODEL,
            "members": "members",  # the ensemble's other models, members/ckpt_<i>.pt (i >= 1)
            "subbands": "subbands",
        },
    ),  # Haar subbands of the training views, subbands/{ref,render}/<stem>.exr
    Stage(
        "mask_data",
        "2_mask_data",
        "mask-data",
        MaskDataConfig,
        ("scene", "coarse"),
        "s2_mask_data:run_mask_data",
        {"index": "index.json"},
    ),  # the corrupted / clean pairs, paths relative to it
    Stage(
        "finetune",
        "3_finetune",
        "finetune",
        FinetuneConfig,
        ("coarse", "mask_data"),
        "s3_finetune:run_finetune",
        {"models": "."},
    ),  # D/ (or D_lora/) and U/
    Stage(
        "repair",
        "4_repair",
        "repair",
        RepairConfig,
        ("scene", "coarse", "finetune"),
        "s4_repair:run_repair",
        {
            "views": "views.json",  # the pseudo views' cameras and weights (and S's silhouette files)
            "silhouettes": "silhouettes",  # per pseudo view, where the object may be (black: S is sure of background)
            "carved_hull": "carved_hull.npz",  # the visual hull carved by V and S (shape.hull.save_grid)
            "pseudo": "pseudo",  # the pseudo references, <stem>.exr (RGB, float) and <name> (PNG)
            "contact_sheet": "contact_sheet.png",
        },
    ),
    # fine rounds run the repair again, so it reads finetune's models too
    Stage(
        "fine",
        "5_fine",
        "fine",
        FineConfig,
        ("scene", "coarse", "finetune", "repair"),
        "s5_fine:run_fine",
        dict(_MODEL),
    ),
    Stage(
        "baseline",
        "baseline",
        "baseline",
        BaselineConfig,
        ("scene", "coarse", "fine"),
        "baseline:run_baseline",
        {"model": _MODEL["model"], "curve": _MODEL["curve"]},
        method=False,
        on_request=True,
    ),
    Stage(
        "eval",
        "6_eval",
        "eval",
        EvalConfig,
        ("scene", "coarse", "repair", "fine", "baseline"),
        "s6_eval:run_eval",
        {"results": "results.json", "report": "report.md", "report_html": "report.html"},
        method=False,
    ),
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
_FAST_TRAIN = {
    "refine_start": 100,
    "refine_every": 50,
    "sh_degree": 1,
    "sh_increase_every": 200,
    "init_points": 3000,
    "hull_resolution": 64,
    "max_gaussians": 20000,
    "floater_every": 200,
    "half_size_until": 0.0,
}

PRESETS: dict[str, dict[str, dict[str, Any]]] = {
    "fast": {
        # 400 iterations leave the held-out rule's pilots (about a model's cost) nothing to save
        "coarse": {**_FAST_TRAIN, "iterations": 400, "refine_stop": 300, "ensemble": 1, "stop": "iterations"},
        "mask_data": {
            **_FAST_TRAIN,
            "iterations": 200,
            "refine_stop": 150,
            "warmup": 60,
            "pair_every": 28,
            "drift_period": 100.0,
        },
        "finetune": {
            "d_steps": 300,
            "u_max_steps": 100,
            "d_channels": 16,
            "u_eval_every": 25,
            "u_patience": 2,
            "prior_steps": 15,
        },
        "repair": {"steps": 5, "num_views": 16, "band_above": 25.0},
        "fine": {**_FAST_TRAIN, "iterations": 300, "refine_start": 50, "refine_stop": 200},
    },
    "default": {},
    "paper": {
        "coarse": {
            "iterations": 10000,
            "refine_stop": 7000,
            "sh_degree": 3,
            "max_gaussians": 1000000,
            "init_points": 100000,
            "hull_resolution": 128,
            "reset_every": 3000,
            "stop": "iterations",  # the paper's schedule, run to its end
        },
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


def resolve(
    stage: str, preset: str | None = None, file_cfg: dict[str, Any] | None = None, cli: dict[str, Any] | None = None
) -> Any:
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


def _facts_by_field(key: str) -> dict[str, Any]:
    """`key` ("choices" or "range") of every stage config's fields that declare it, by field name
    (one name, one fact, whichever stage's config holds it)."""
    out: dict[str, Any] = {}
    for cls in STAGES.values():
        for f in dataclasses.fields(cls):
            value = facts(cls, f.name).get(key)
            if value is not None:
                if out.setdefault(f.name, value) != value:
                    raise AssertionError(f"field {f.name} declares two {key}")
    return out


# the allowed values of a text field, and the allowed range of a numeric one (inclusive, None:
# open), as the fields declare them (`fields.option`)
CHOICES: dict[str, tuple[str, ...]] = _facts_by_field("choices")
RANGES: dict[str, tuple[float, float | None]] = _facts_by_field("range")


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
