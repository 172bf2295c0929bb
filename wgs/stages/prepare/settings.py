"""The prepare stage's settings, its facts for the registry and its cost model."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from ...cost import CPU_TARGET_S, GPU_MAX_SIZE, Calibration, SceneFacts, StageCost
from ...fields import option
from ...scene.learned_matching import MATCH_SIDE
from ...scene.sfm import HOLD_EXIF_FOCAL
from ...segment.accept import MaskParams
from ..stage import Stage, StageEnv

PREPARE_S_PER_MEGAPIXEL = 0.08  # reading, undistorting and downscaling a photo, per full-size megapixel


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
    # a few photos posed by learned matching keep the focal length their EXIF gives (false: bundle
    # adjustment refines it from there); a photo cropped after it was taken keeps its uncropped EXIF
    hold_exif_focal: bool = HOLD_EXIF_FOCAL
    # learned matching on photos resized to this long side (px; smaller photos are enlarged to it)
    match_side: int = option(MATCH_SIDE, bounds=(64, None))
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


def run(ws: Any, cfg: PrepareConfig, env: StageEnv, force: bool) -> bool:
    from .run import run_prepare  # on first use: the stage loads the library

    return run_prepare(ws, cfg, env, force)


def cost(cal: Calibration, cfgs: Mapping[str, Any], facts: SceneFacts, before: Mapping[str, float]) -> StageCost:
    photos_s = PREPARE_S_PER_MEGAPIXEL * (facts.n_train + facts.n_test) * facts.full_pixels / 1e6
    return StageCost(fixed_steps=20, other_s=photos_s)


STAGE = Stage(
    "prepare",
    "scene",
    PrepareConfig,
    (),
    run,
    "Import SCENE (COLMAP, Blender, instant-ngp/nerfstudio, IDR, LLFF, or photos without poses,\n"
    "which structure-from-motion poses) into the workspace.",
    cost,
    outputs={
        "prepared": ".",
        "info": "scene.json",
        "masks_sheet": "masks_sheet.png",  # automatic masks: the training photos with their outline
        "masks_proposed": "masks_proposed",  # automatic masks not used (auto_failed): to correct
    },
    all_options=("views", "downscale", "max_size", "matcher", "focal", "fov", "cameras", "masks", "mirror"),
)
