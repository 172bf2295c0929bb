"""Read a prepared workspace scene back: frames with tensors in the normalised world."""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path

import torch

from ..errors import InputError
from ..io import read_json
from ..io.images import read_image
from .camera import Camera
from .colmap import read_model
from .convention import Normalisation
from .mirror import MirrorPlane, mirror_frame


@dataclass(kw_only=True)
class Frame(Camera):
    """One prepared view: a Camera (in the normalised world) plus its name and images. Tensors are
    float32 on the CPU.

    Attributes:
        name: image name in the workspace.
        image: [H, W, 3] straight (not premultiplied) colour in [0, 1], or None if not loaded.
        mask: [H, W] in [0, 1], or None.
        shows_colour: whether the image shows the object's colours from this camera; False for a view
            whose mask only says where the object is not (an "outline" mirror view: training carves
            with it, see `gaussians.trainer`).
    """

    name: str
    image: torch.Tensor | None = None
    mask: torch.Tensor | None = None
    shows_colour: bool = True

    @property
    def pixels(self) -> torch.Tensor:
        """The image, for code that needs it loaded (training views, test views being scored)."""
        if self.image is None:
            raise ValueError(f"{self.name}: image not loaded")
        return self.image

    @property
    def object_pixels(self) -> torch.Tensor:
        """The mask's object pixels (bool [H, W]), for code that needs a mask."""
        if self.mask is None:
            raise ValueError(f"{self.name}: no mask")
        return self.mask > 0.5


def halved(frame: Frame) -> Frame:
    """The frame at half its size (odd sizes drop their last row or column): each pixel the mean of
    a 2x2 block, so that compositing on a background commutes with the halving (the colour is
    averaged premultiplied by the mask); the intrinsics halved, since pixel centres lie at +0.5."""

    def pool(t: torch.Tensor) -> torch.Tensor:  # [H, W, C] -> [H/2, W/2, C]
        return torch.nn.functional.avg_pool2d(t.permute(2, 0, 1)[None], 2)[0].permute(1, 2, 0)

    K = frame.K.clone()
    K[:2] *= 0.5
    mask = pool(frame.mask[..., None])[..., 0] if frame.mask is not None else None
    image = frame.image
    if image is not None:
        if frame.mask is None or mask is None:
            image = pool(image)
        else:
            covered = pool(image * frame.mask[..., None])
            image = torch.where(mask[..., None] > 0, covered / mask[..., None].clamp_min(1e-12), pool(image))
    return replace(frame, K=K, width=frame.width // 2, height=frame.height // 2, image=image, mask=mask)


@dataclass
class PreparedScene:
    info: dict
    norm: Normalisation
    train: list[Frame]
    test: list[Frame]

    @property
    def photos(self) -> list[Frame]:
        """The training views that are the scene's own photos (not mirror views)."""
        names = set(self.info["train_names"])
        return [f for f in self.train if f.name in names]

    @property
    def colour_views(self) -> list[Frame]:
        """The training views whose images show the object's colours (all but outline-only views)."""
        return [f for f in self.train if f.shows_colour]

    @property
    def has_masks(self) -> bool:
        return bool(self.info.get("has_masks"))


def load_frame_images(sdir: Path, frames: list[Frame]) -> list[Frame]:
    """The frames with their image (and mask, when the scene has one) read from the prepared scene
    folder `sdir` (a workspace's scene/)."""
    for f in frames:
        f.image = torch.from_numpy(read_image(sdir / "images" / f.name)[..., :3].copy())
        mpath = sdir / "masks" / f.name
        if mpath.is_file():
            f.mask = torch.from_numpy(read_image(mpath)[..., 0].copy())
    return frames


def load_prepared(sdir: Path, load_test_images: bool = False) -> PreparedScene:
    """The scene `wgs prepare` wrote to the folder `sdir` (a workspace's scene/)."""
    if not (sdir / "scene.json").is_file():
        raise InputError("no prepared scene: run `wgs prepare SCENE -w WS` first", sdir)
    info = read_json(sdir / "scene.json")
    model = read_model(sdir / "sparse")

    def frames(names: list[str], with_images: bool) -> list[Frame]:
        out = []
        for n in names:
            if n not in model:
                raise InputError(f"image {n} is not in the COLMAP model", sdir / "sparse")
            c = model[n]
            out.append(Frame(c.K.float(), c.viewmat.float(), c.width, c.height, name=n))
        return load_frame_images(sdir, out) if with_images else out

    train = frames(info["train_names"], True)
    mirror = info.get("mirror") or {}
    if mirror.get("used"):  # the photos' mirror images are training views too (shape.symmetry)
        plane = MirrorPlane.from_json(mirror["plane"])
        train += [mirror_frame(f, plane, shows_colour=mirror.get("views") == "full") for f in train]
    return PreparedScene(
        info, Normalisation.from_json(info["normalisation"]), train, frames(info["test_names"], load_test_images)
    )


def composite(image: torch.Tensor, mask: torch.Tensor | None, background: torch.Tensor) -> torch.Tensor:
    """[H, W, 3] straight colour over a background [3] through mask [H, W]."""
    if mask is None:
        return image
    a = mask[..., None]
    return image * a + background * (1 - a)


__all__ = ["Frame", "PreparedScene", "load_prepared", "composite"]
