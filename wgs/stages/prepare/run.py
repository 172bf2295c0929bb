"""Stage 0: import a scene into `WS/scene/`; photos without poses are first posed into `WS/sfm/`."""

from __future__ import annotations

import dataclasses
import hashlib
import math
import statistics
from pathlib import Path

import torch

from ...errors import InputError
from ...gaussians.pose_refine import CameraCorrections
from ...gaussians.trainer import train_gaussians
from ...io import atomic_write_bytes, atomic_write_json, read_json
from ...io.images import image_size, write_png
from ...progress import log
from ...scene.colmap import read_model, write_model
from ...scene.dataset import load_prepared
from ...scene.formats import detect_format
from ...scene.prepare import (
    MASK_MIN_FRACTION,
    LoadedViews,
    downscale_for,
    given_mask_share,
    load_scene_for_prepare,
    load_views,
    scene_inputs_digest,
    write_prepared,
)
from ...scene.sfm import find_photos, pose_photos
from ...scene.types import RawScene
from ...segment.accept import judged_automatic_masks
from ...segment.automask import mask_sheet
from ...shape.scores import HULL_CUT_LIMIT, leave_one_out, mean_scores
from ...shape.symmetry import mirror_check
from ...threads import thread_count
from ...workspace import StageRun, Workspace
from ..coarse.settings import CoarseConfig
from ..shared import initial_splats
from ..stage import StageEnv
from .settings import PrepareConfig

SFM_DIR = "sfm"
SFM_INPUTS = "inputs.sha256"
SFM_SUMMARY = "summary.json"
MASK_MODES = ("auto", "none")  # PrepareConfig.masks: these, or a folder of masks


def mask_folder(cfg: PrepareConfig) -> Path | None:
    return None if cfg.masks in MASK_MODES else Path(cfg.masks)


def _photos_digest(image_dir: Path, names: list[str], mask_dir: Path | None, cfg: PrepareConfig) -> str:
    h = hashlib.sha256(
        f"sfm-3:{cfg.matcher}:{cfg.sfm_max_image_size}:{cfg.match_side}:{cfg.focal}:{cfg.fov}:{cfg.hold_exif_focal}".encode()
    )
    for folder in (image_dir, mask_dir):
        for p in sorted(folder.iterdir()) if folder is not None else ():
            if p.is_file() and (folder != image_dir or p.name in names):
                st = p.stat()
                h.update(f"{p.name}:{st.st_size}:{st.st_mtime_ns}".encode())
    return h.hexdigest()


def known_focal(cfg: PrepareConfig, image_dir: Path, names: list[str]) -> float | None:
    """The photos' focal length in pixels from --focal or --fov (of the first photo's width), or None."""
    if cfg.focal is not None and cfg.fov is not None:
        raise InputError("give --focal or --fov, not both")
    if cfg.fov is not None:
        width, _ = image_size(image_dir / names[0])
        return 0.5 * width / math.tan(math.radians(cfg.fov) / 2)
    return cfg.focal


def posed_photos(ws: Workspace, scene_dir: Path, cfg: PrepareConfig) -> Path:
    """The COLMAP model of the photos in `scene_dir`, made once by structure-from-motion and kept
    in `WS/sfm/` until the photos or the settings change."""
    out = ws.root / SFM_DIR
    found = find_photos(scene_dir)
    if found is None:
        raise InputError("no photos found", scene_dir)
    image_dir, names, mask_dir = found
    key = _photos_digest(image_dir, names, mask_dir, cfg)
    if (out / SFM_INPUTS).is_file() and (out / SFM_INPUTS).read_text().strip() == key:
        log("sfm: photos already posed, reused")
        return out
    log(f"sfm: posing {len(names)} photos{' inside their masks' if mask_dir else ''} (pycolmap, CPU)")
    with ws.lock():
        res = pose_photos(
            image_dir,
            names,
            mask_dir,
            out,
            cfg.matcher,
            cfg.sfm_max_image_size,
            thread_count(),
            known_focal(cfg, image_dir, names),
            cfg.match_side,
            cfg.hold_exif_focal,
        )
        atomic_write_json(
            out / SFM_SUMMARY,
            {
                "registered": res.registered,
                "photos": res.total,
                "seconds": round(res.seconds, 2),
                "matcher": res.matcher,
            },
        )
        atomic_write_bytes(out / SFM_INPUTS, (key + "\n").encode())
    return out


def run_prepare(ws: Workspace, cfg: PrepareConfig, env: StageEnv, force: bool = False) -> bool:
    """Import `env.scene_dir`; returns False when the workspace was already up to date."""
    scene_dir = env.scene_dir
    if scene_dir is None:
        raise InputError("prepare needs a scene folder")
    sfm_model = (
        posed_photos(ws, scene_dir, cfg) if scene_dir.is_dir() and detect_format(scene_dir) == "photos" else None
    )
    scene = load_scene_for_prepare(scene_dir, cfg.views, cfg.test_every, mask_folder(cfg), sfm_model)
    learned = False
    if sfm_model is not None:
        s = read_json(sfm_model / SFM_SUMMARY)
        learned = s["matcher"] == "learned"
        scene.notes.append(
            f"poses by structure-from-motion: {s['registered']} of {s['photos']} photos registered "
            f"({s['matcher']} matching, {s['seconds']:.0f} s); the model is in {sfm_model}"
        )
    extra = {
        "source": str(scene_dir.resolve()),
        "inputs": scene_inputs_digest(scene),
        "working_size": env.working_size.key if env.working_size and not (cfg.downscale or cfg.max_size) else None,
    }

    def body(run: StageRun) -> str:
        k, why = working_downscale(scene, cfg, env)
        if why:
            log(why)
            run.record["working_size"] = why
        return import_scene(run, ws, scene_dir, scene, dataclasses.replace(cfg, downscale=k), force, env, learned)

    return ws.run_staged("prepare", cfg, extra, force, body)


def working_downscale(scene: RawScene, cfg: PrepareConfig, env: StageEnv) -> tuple[int, str | None]:
    """The integer downscale of the photos, and the line that says why where wgs chose it: `downscale`,
    else from `max_size`, else the size chosen for the machine (`env.working_size`), else 1."""
    if cfg.downscale:
        return cfg.downscale, None
    v = scene.views[scene.train[0]]
    if cfg.max_size:
        k = downscale_for(v.width, v.height, cfg.max_size)
        return k, (
            f"working size: {v.width // k}x{v.height // k} (the photos' {v.width}x{v.height} / {k}: "
            f"--max-size {cfg.max_size})"
        )
    if env.working_size is None:
        return 1, None
    has_masks = cfg.masks != "none"
    share = given_mask_share(scene, cfg.max_pixels) if has_masks else None
    return env.working_size(v.width, v.height, len(scene.train), len(scene.test), has_masks, share)


def scene_masks(views: LoadedViews, cfg: PrepareConfig, run: StageRun) -> tuple[list, dict, list]:
    """The masks to use, their record, and the masks the crop check judges (those used, or the
    automatic ones proposed). Automatic masks that are not used are written for correction
    (`masks_proposed`); all are outlined on the training photos (`masks_sheet`)."""
    given = any(m is not None for m in views.masks)
    source = "folder" if mask_folder(cfg) is not None else "given" if given else cfg.masks
    if source != "auto":
        return views.masks, {"source": source}, views.masks
    names, n = views.names, views.n_train
    judged = judged_automatic_masks(
        views.images, [views.cameras[name] for name in names], names, n, cfg, thread_count(), MASK_MIN_FRACTION
    )
    if judged.used is None:  # not used, but there to be corrected and given back (--masks DIR)
        for name, mask in zip(names, judged.proposed, strict=True):
            write_png(run.output("masks_proposed", name), mask)
    write_png(run.output("masks_sheet"), mask_sheet(views.images[:n], judged.proposed[:n]))
    used = judged.used if judged.used is not None else views.masks
    return used, judged.record, judged.proposed


def mask_line(masks: dict, sheet: Path, proposed: Path) -> str:
    """Which masks the scene uses, in one line; `sheet` and `proposed`: where the automatic masks'
    contact sheet and, when they were not used, the masks themselves are."""
    if masks["source"] == "auto":
        m = masks["model"]
        return (
            f"masks: automatic ({m['package'] or m['file']}{' ' + m['version'] if m['version'] else ''}, "
            f"agreement between views cut {100 * masks['cut_by_agreement']['mean']:.1f} % of the network's "
            f"object area, {masks['seconds_per_photo']:.1f} s per photo"
            + (
                "; the other views support nothing of the network's mask of "
                f"{', '.join(masks['without_agreement'])}: what they alone call object there"
                if masks["without_agreement"]
                else ""
            )
            + (
                f"; {', '.join(masks['not_voting'])} did not vote (the others hold too little of their mask)"
                if masks.get("not_voting")
                else ""
            )
            + f"); check them in {sheet}, correct them with --masks DIR"
        )
    if "auto_failed" in masks:
        return (
            f"masks: none ({masks['auto_failed']}; --masks DIR takes yours; the automatic ones are in "
            f"{proposed} to correct, outlined in {sheet})"
        )
    return {
        "given": "masks: the scene's own",
        "folder": "masks: from the --masks folder",
        "none": "masks: none (--masks none)",
    }[masks["source"]]


def poses_agree_with_masks(scene_dir: Path, photos_dir: Path) -> None:
    """Photos posed from a few wide-baseline matches can be placed wrongly, and then the visual hull
    of the other photos' masks leaves out much of a photo's own mask: more than HULL_CUT_LIMIT on
    average is refused, naming the photos it cuts most (generated object, 4 photos: right poses
    0.01-0.3 %, wrong ones 20-30 %)."""
    photos = load_prepared(scene_dir).photos
    advice = (
        "the photos are probably too far apart to pose; take photos closer together (neighbours up to about 45 "
        "degrees apart), or give the cameras"
    )
    try:
        per_photo = leave_one_out(photos, HULL_CHECK_RESOLUTION)
    except InputError:
        raise InputError(
            f"the poses found disagree with the masks: under them the masks share no region: {advice}", photos_dir
        ) from None
    cut = mean_scores(per_photo)
    if cut is None or cut["missed"] <= HULL_CUT_LIMIT:
        return
    worst = sorted(per_photo, key=lambda n: -per_photo[n]["missed"])[:2]
    raise InputError(
        "the poses found disagree with the masks: the hull of the other photos leaves out "
        + ", ".join(f"{100 * per_photo[n]['missed']:.0f} % of {n}'s mask" for n in worst)
        + f" (on average {100 * cut['missed']:.1f} %, at most {100 * HULL_CUT_LIMIT:.0f} % for poses that fit): "
        + advice,
        photos_dir,
    )


HULL_CHECK_RESOLUTION = 96  # the pose check's hull grid (voxels a side)


def unchecked_poses_line(n_photos: int, mask_source: str) -> str | None:
    """The line for photos wgs posed from a few views where no masks of the user's can check the
    poses (`mask_source` "auto" or "none"); None where they can. Automatic masks are made under the
    poses, so they agree with wrong ones: 4 generated photos of a box, a mug, a cabinet and a vase
    in a room, posed 129-154 degrees off (their textures repeat), left the automatic masks' vote
    cutting 0.6-9.8 % of the network's object area, against 0.3-3.5 % at the true cameras and
    12.9 % at ethiopianHead's (README, "Photos that repeat")."""
    if mask_source not in ("auto", "none"):
        return None
    return (
        f"cameras: posed by wgs from {n_photos} photos without masks of yours, so nothing checks the poses: "
        "repeating textures or a symmetric object can be posed wrongly, and masks made under the poses agree "
        "with them; with masks of your own (masks/ beside images/, or --masks DIR) the hull of the other "
        "photos checks each pose"
    )


# a correction is kept unless the hull of the other photos leaves out more of a photo's mask than
# this beyond the posed cameras' share (right poses measure 0.01-0.3 % at 96 cells a side, README)
CAMERA_MISSED_TOLERANCE = 0.001


def hull_missed(photos) -> float:
    """The mean share of a photo's mask that the hull of the other photos leaves out."""
    scores = mean_scores(leave_one_out(photos, HULL_CHECK_RESOLUTION))
    return scores["missed"] if scores is not None else 0.0


def correct_cameras(scene_dir: Path, cfg: PrepareConfig, device: torch.device, seed: int = 0) -> dict:
    """Photos posed from a few views: their cameras corrected by training one coarse model (the
    defaults' schedule) on them with `CameraCorrections` (the first camera held). The correction
    is written into the prepared scene's model unless the hull of the other photos then leaves
    out more of each photo's mask (`leave_one_out`, as the pose check measures it, beyond
    CAMERA_MISSED_TOLERANCE). One line says which, and why."""
    scene = load_prepared(scene_dir)
    photos = scene.train
    coarse = dataclasses.replace(CoarseConfig(), iterations=cfg.camera_iterations)
    cams = CameraCorrections(len(photos), cfg.camera_lr, device)
    train_gaussians(
        initial_splats(scene, coarse, seed),
        photos,
        coarse,
        device,
        extent=1.0,
        desc="cameras",
        seed=seed,
        has_masks=True,
        cameras=cams,
    )
    moved = cams.viewmats([f.viewmat for f in photos])
    corrected = [dataclasses.replace(f, viewmat=v) for f, v in zip(photos, moved, strict=True)]
    before, after = (hull_missed(views) for views in (photos, corrected))
    turns = [math.degrees(float(w.norm())) for w in cams.omega.detach()[1:]]  # the first camera is held
    record = {
        "kept": after <= before + CAMERA_MISSED_TOLERANCE,
        "hull_missed_posed": round(before, 6),
        "hull_missed_corrected": round(after, 6),
        "median_turn_deg": round(statistics.median(turns), 4),
    }
    agree = (
        f"the hull of the other photos leaves out {100 * after:.2f} % of a photo's mask ({100 * before:.2f} % as posed)"
    )
    if record["kept"]:
        model = read_model(scene_dir / "sparse")
        for f, delta in zip(photos[1:], cams.deltas()[1:], strict=True):  # the stored poses, in float64
            model[f.name] = dataclasses.replace(model[f.name], viewmat=delta @ model[f.name].viewmat.double())
        write_model(scene_dir / "sparse", model)
        log(f"cameras: corrected by training (median turn {record['median_turn_deg']:.2f} deg): {agree}")
    else:
        log(f"cameras: kept as posed: corrected by training, {agree}")
    return record


def find_mirror_views(scene_dir: Path, cfg: PrepareConfig) -> dict | None:
    """The mirror check on the prepared training views (`shape.symmetry.mirror_check`), in one line;
    None where the masks share no region."""
    frames = load_prepared(scene_dir).train
    try:
        record = mirror_check(frames, cfg.mirror_min_gain, cfg.mirror_max_missed, cfg.mirror_directions)
        record["views"] = cfg.mirror
    except InputError:
        log("mirror: the training masks share no region -> no mirror views")
        return None
    ious = (
        f"leave-one-out silhouette IoU {record['leave_one_out_iou']:.3f} -> {record['leave_one_out_iou_mirrored']:.3f}"
    )
    if record["used"]:
        taught = "their outlines" if cfg.mirror == "outline" else "their outlines and colours"
        log(
            f"mirror: the {len(frames)} training photos' mirror images join them as training views, teaching "
            f"{taught} ({ious})"
        )
    elif record["missed"] > cfg.mirror_max_missed:
        log(
            f"mirror: the best mirror plane ({ious}) would cut {100 * record['missed']:.1f} % of the photos' masks "
            "-> no mirror views"
        )
    else:
        log(f"mirror: no mirror plane raises the {ious} by {cfg.mirror_min_gain} -> no mirror views")
    return record


def import_scene(
    run: StageRun,
    ws: Workspace,
    scene_dir: Path,
    scene: RawScene,
    cfg: PrepareConfig,
    force: bool,
    env: StageEnv,
    check_poses: bool = False,
) -> str:
    """`check_poses`: poses from learned matching of a few photos, which the masks then check and
    training then corrects (`correct_cameras`, on `env.device`)."""
    held = ((ws.manifest("prepare") or {}).get("summary") or {}).get("source")
    if held is not None and Path(held) != scene_dir.resolve() and not force:
        raise InputError(
            f"this workspace holds another scene ({held}): use a new -w folder, or add --force "
            "to replace it (every stage is then recomputed)",
            ws.root,
        )
    for note in scene.notes:
        log(f"  note: {note}")
    log(f"prepare: {scene.format} scene, {len(scene.train)} training + {len(scene.test)} test views")
    views = load_views(scene, cfg.downscale or 1, cfg.max_pixels, run.dir)
    masks, mask_info, judged = scene_masks(views, cfg, run)
    info = write_prepared(scene, views, masks, mask_info, judged, run.dir)
    log(mask_line(info["masks"], ws.output("prepare", "masks_sheet"), ws.output("prepare", "masks_proposed")))
    unchecked = unchecked_poses_line(len(info["train_names"]), info["masks"]["source"]) if check_poses else None
    if unchecked is not None:
        log(unchecked)
        info["poses_checked"] = False
        atomic_write_json(run.dir / "scene.json", info)
    if check_poses and info["has_masks"] and info["masks"]["source"] != "auto":
        poses_agree_with_masks(run.dir, scene_dir)
        if cfg.cameras == "correct":
            info["cameras_corrected"] = correct_cameras(run.dir, cfg, env.device, env.seed)
            atomic_write_json(run.dir / "scene.json", info)
    cropped, n = info["masks"]["training_cropped"], len(info["train_names"])
    if cropped:
        log(
            f"masks: the object reaches the frame's edge in {len(cropped)} of the {n} training photos "
            f"({', '.join(cropped)}): photos that hold the whole object bound more of it (--views N takes the "
            "ones sparse_N.txt names)"
        )
    if cfg.mirror != "none" and info["has_masks"]:
        info["mirror"] = find_mirror_views(run.dir, cfg)
        atomic_write_json(run.dir / "scene.json", info)
    run.record["summary"] = {
        "source": info["source"],
        "format": info["format"],
        "num_train": len(info["train_names"]),
        "num_test": len(info["test_names"]),
        "resolution": info["resolution"],
        "has_masks": info["has_masks"],
        "masks": info["masks"],
        "mirror": info.get("mirror"),
    }
    return f"prepare: wrote {ws.stage_dir('prepare')}"


# what tools and other packages may use; the rest is this stage's own
__all__ = ["run_prepare"]
