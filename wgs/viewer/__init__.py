"""`wgs view`: the trained model in the browser. A localhost-only server hands out one page, the
vendored WebGL splat viewer (gsplat.js 1.2.9 from npm, MIT, `static/LICENSE.gsplat`), the model as
a `.splat` turned so that the object stands upright around the origin, and the eval report.
"""

from __future__ import annotations

import contextlib
import http.server
import json
import threading
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from ..errors import InputError

STATIC = Path(__file__).parent / "static"
TYPES = {
    ".html": "text/html; charset=utf-8",
    ".js": "text/javascript; charset=utf-8",
    ".json": "application/json",
    ".splat": "application/octet-stream",
    ".png": "image/png",
    ".gif": "image/gif",
}


@dataclass
class ViewerFrame:
    """Where the viewer puts the model: x_viewer = R @ x_world + t (y down, the object upright at
    the origin), and the first training camera's orbit (gsplat.js OrbitControls angles)."""

    R: np.ndarray  # [3, 3]
    t: np.ndarray  # [3]
    alpha: float
    beta: float
    radius: float


def viewer_frame(w2cs: list[np.ndarray]) -> ViewerFrame:
    """From the training cameras (world-to-camera OpenCV [4, 4]): up is their mean up, the object
    centre the point nearest their optical axes, the start view the first camera's."""
    from ..scene.camera import camera_center
    from ..scene.convention import look_at_center

    Rs = np.stack([m[:3, :3] for m in w2cs])
    centers = np.stack([camera_center(m) for m in w2cs])
    center = look_at_center(centers, Rs[:, 2, :])
    up = -Rs[:, 1, :].mean(0)
    up /= max(np.linalg.norm(up), 1e-12)
    to_obj = center - centers[0]
    fwd = to_obj - up * (to_obj @ up)  # horizontal, from the first camera towards the object
    if np.linalg.norm(fwd) < 1e-9:  # looking straight down: any horizontal direction
        fwd = np.cross(up, [1.0, 0.0, 0.0]) if abs(up[0]) < 0.9 else np.cross(up, [0.0, 1.0, 0.0])
    fwd /= np.linalg.norm(fwd)
    right = np.cross(-up, fwd)  # x = y cross z with y = down, z = forward
    R = np.stack([right, -up, fwd])
    t = -R @ center
    cam = R @ centers[0] + t
    radius = float(np.linalg.norm(cam))
    beta = float(np.arcsin(np.clip(-cam[1] / max(radius, 1e-12), -1, 1)))
    return ViewerFrame(R, t, 0.0, beta, radius)


def model_path(ws, stage: str | None) -> tuple[str, Path]:
    from ..stages.shared import newest_model

    stage = stage or newest_model(ws)
    path = ws.output(stage, "model")
    if ws.manifest(stage) is None or not path.is_file():
        raise InputError(f"no {stage} model: run `wgs {stage}` (or `wgs all`) first", ws.stage_dir(stage))
    return stage, path


def site(ws, stage: str | None) -> dict[str, bytes | Path]:
    """Every file the viewer serves: {url path: bytes or a file}."""
    from ..gaussians.splats import load_checkpoint, splat_bytes
    from ..scene.dataset import load_prepared

    stage, ckpt = model_path(ws, stage)
    scene = load_prepared(ws.output("prepare", "prepared"))
    splats, _ = load_checkpoint(ckpt, scene.norm)  # normalised world, like the cameras
    report = ws.output("eval", "report_html")
    frame = viewer_frame([f.viewmat.double().numpy() for f in scene.train])
    first = scene.train[0]
    files: dict[str, bytes | Path] = {
        "/": (STATIC / "index.html"),
        "/gsplat.es.js": STATIC / "gsplat.es.js",
        "/LICENSE.gsplat": STATIC / "LICENSE.gsplat",
        "/model.splat": splat_bytes(splats, torch.from_numpy(frame.R), torch.from_numpy(frame.t)),
        "/view.json": json.dumps(
            {
                "stage": stage,
                "gaussians": int(splats["means"].shape[0]),
                "alpha": frame.alpha,
                "beta": frame.beta,
                "radius": frame.radius,
                "focal": float(first.K[1, 1]) / first.height,  # the photos' field of view
                "report": report.is_file(),
            }
        ).encode(),
    }
    if report.is_file():
        files["/report.html"] = report
    return files


class _Handler(http.server.BaseHTTPRequestHandler):
    files: dict[str, bytes | Path] = {}

    def do_GET(self) -> None:  # noqa: N802 (http.server's name)
        path = self.path.split("?", 1)[0]
        body = self.files.get(path)
        if body is None:
            self.send_error(404)
            return
        data = body.read_bytes() if isinstance(body, Path) else body
        name = body.name if isinstance(body, Path) else path
        kind = TYPES.get(Path(name).suffix, "application/octet-stream")
        self.send_response(200)
        self.send_header("Content-Type", kind)
        self.send_header("Content-Length", str(len(data)))
        self.send_header("Cache-Control", "no-store")
        self.end_headers()
        self.wfile.write(data)

    def log_message(self, *args) -> None:  # quiet: the command prints its address once
        pass


@contextlib.contextmanager
def serving(files: dict[str, bytes | Path], port: int = 0) -> Iterator[str]:
    """Serve `files` on 127.0.0.1 (never another interface) in a thread; yields the base URL."""
    handler = type("Handler", (_Handler,), {"files": files})
    try:
        server = http.server.ThreadingHTTPServer(("127.0.0.1", port), handler)
    except OSError as exc:
        raise InputError(f"cannot serve on 127.0.0.1:{port} ({exc.strerror})") from None
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    try:
        yield f"http://127.0.0.1:{server.server_address[1]}/"
    finally:
        server.shutdown()
        server.server_close()


__all__ = ["viewer_frame", "site", "serving", "ViewerFrame", "model_path"]
