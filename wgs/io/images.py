"""Image and mask files (OpenImageIO): read, area-downscale, write."""

from __future__ import annotations

import contextlib
import os
from pathlib import Path

import numpy as np
import OpenImageIO as oiio

from ..errors import InputError
from .files import atomic_path

IMAGE_EXTS = (".png", ".jpg", ".jpeg", ".exr", ".tif", ".tiff", ".bmp", ".webp")


def oiio_path(path: Path) -> str:
    """The path as OpenImageIO takes it (UTF-8 text); a name in another encoding is refused clearly."""
    text = str(path)
    try:
        text.encode("utf-8")
    except UnicodeEncodeError:
        raise InputError("file name is not valid UTF-8: rename the file", path) from None
    return text


@contextlib.contextmanager
def decoder_stderr_silenced():
    """Decoder libraries (libpng, libjpeg) print their own lines on fd 2; our one error line says
    it instead. Redirects the process's fd 2 for the duration (nothing else prints meanwhile)."""
    try:
        saved = os.dup(2)
    except OSError:  # no fd 2 (embedded interpreters): nothing to silence
        yield
        return
    try:
        with open(os.devnull, "wb") as null:
            os.dup2(null.fileno(), 2)
        yield
    finally:
        os.dup2(saved, 2)
        os.close(saved)


def image_size(path: Path) -> tuple[int, int]:
    """(width, height) from the header, without decoding pixels."""
    with decoder_stderr_silenced():
        inp = oiio.ImageInput.open(oiio_path(path))
    if inp is None:
        raise InputError(f"cannot read image ({_oiio_error()})", path)
    spec = inp.spec()
    inp.close()
    return spec.width, spec.height


def read_image(path: Path, max_pixels: int | None = None) -> np.ndarray:
    """Decode an image to float32 [H, W, C] in [0, 1] (C = 1, 3 or 4; 8/16-bit or float files)."""
    if not path.is_file():
        raise InputError("image file not found", path)
    with decoder_stderr_silenced():
        inp = oiio.ImageInput.open(oiio_path(path))
        if inp is None:
            raise InputError(f"cannot read image ({_oiio_error()})", path)
        try:
            spec = inp.spec()
            if max_pixels is not None and spec.width * spec.height > max_pixels:
                raise InputError(
                    f"image is {spec.width}x{spec.height}, above the limit of {max_pixels} pixels "
                    "(raise it with --max-pixels)",
                    path,
                )
            data = inp.read_image(0, 0, 0, spec.nchannels, "float")
            err = inp.geterror() if hasattr(inp, "geterror") else ""
        finally:
            inp.close()
    if data is None or not isinstance(data, np.ndarray) or err:
        why = one_line(err) or _oiio_error() or "no pixel data"
        raise InputError(f"truncated or corrupt image ({why})", path)
    if data.ndim == 2:
        data = data[..., None]
    if not np.isfinite(data).all():
        raise InputError("image holds NaN or infinite values", path)
    return np.ascontiguousarray(data, dtype=np.float32)


def split_rgba(img: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
    """[H, W, C] -> RGB [H, W, 3] and alpha [H, W] (or None)."""
    c = img.shape[-1]
    if c == 1:
        return np.repeat(img, 3, axis=-1), None
    if c == 2:
        return np.repeat(img[..., :1], 3, axis=-1), img[..., 1]
    if c == 3:
        return img, None
    return img[..., :3], img[..., 3]


def to_mask(img: np.ndarray) -> np.ndarray:
    """A mask file (grey, RGB or RGBA) -> [H, W] float in [0, 1]."""
    if img.shape[-1] == 4:
        # Masks saved as RGBA: the alpha when it is used, else the colour.
        a = img[..., 3]
        return a if a.min() < 1.0 else img[..., :3].mean(-1)
    return img[..., :3].mean(-1) if img.shape[-1] >= 3 else img[..., 0]


def downscale(rgb: np.ndarray, mask: np.ndarray | None, k: int) -> tuple[np.ndarray, np.ndarray | None]:
    """Area-average by an integer factor k; colour is averaged premultiplied by the mask so object
    edges keep no background fringe. Sizes not divisible by k lose their last rows/columns."""
    if k == 1:
        return rgb, mask
    h, w = (rgb.shape[0] // k) * k, (rgb.shape[1] // k) * k
    if h == 0 or w == 0:
        raise ValueError(f"downscale factor {k} is larger than the image ({rgb.shape[1]}x{rgb.shape[0]})")

    def pool(x: np.ndarray) -> np.ndarray:
        x = x[:h, :w]
        return x.reshape(h // k, k, w // k, k, *x.shape[2:]).mean(axis=(1, 3))

    if mask is None:
        return pool(rgb).astype(np.float32), None
    a = pool(mask)
    premult = pool(rgb * mask[..., None])
    out = np.where(a[..., None] > 1e-8, premult / np.maximum(a[..., None], 1e-8), 0.0)
    return out.astype(np.float32), a.astype(np.float32)


def write_gif(path: Path, frames: list[np.ndarray], fps: float = 20.0) -> None:
    """Frames [H, W, 3] float in [0, 1] -> a looping animated GIF (Pillow, which matplotlib brings)."""
    from PIL import Image

    if not frames:
        raise ValueError("write_gif: no frames")
    imgs = [Image.fromarray((np.clip(f[..., :3], 0, 1) * 255 + 0.5).astype(np.uint8)) for f in frames]
    with atomic_path(path) as tmp:
        imgs[0].save(tmp, format="GIF", save_all=True, append_images=imgs[1:], duration=round(1000 / fps), loop=0)


def write_png(path: Path, img: np.ndarray) -> None:
    """Write [H, W] or [H, W, C] float in [0, 1] as an 8-bit PNG (atomically)."""
    if img.ndim == 2:
        img = img[..., None]
    data = np.clip(np.rint(np.clip(img, 0.0, 1.0) * 255.0), 0, 255).astype(np.uint8)
    h, w, c = data.shape
    write_with_oiio(path, data, oiio.ImageSpec(w, h, c, "uint8"), "PNG")


def write_with_oiio(path: Path, data: np.ndarray, spec, what: str) -> None:
    """Write [H, W, C] `data` as `spec` describes it, atomically (a temporary file, then a rename)."""
    with atomic_path(path) as tmp:
        out = oiio.ImageOutput.create(str(tmp))
        if out is None or not out.open(str(tmp), spec):
            raise OSError(f"{path}: cannot write {what}: {_oiio_error()}")
        ok = out.write_image(np.ascontiguousarray(data))
        out.close()
        if not ok:
            raise OSError(f"{path}: cannot write {what}: {_oiio_error()}")


def find_with_stem(folder: Path, stem: str) -> Path | None:
    """The file in `folder` whose name is `stem` plus an image extension (any case)."""
    for ext in IMAGE_EXTS:
        for cand in (folder / f"{stem}{ext}", folder / f"{stem}{ext.upper()}"):
            if cand.is_file():
                return cand
    return None


def one_line(text: str) -> str:
    """A library's multi-line message as one line, repeated lines dropped."""
    lines = [ln.strip() for ln in (text or "").splitlines() if ln.strip()]
    return "; ".join(dict.fromkeys(lines))


def _oiio_error() -> str:
    return one_line(oiio.geterror())
