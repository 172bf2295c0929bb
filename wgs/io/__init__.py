"""The file layer under the workspace and the stages: atomic writes and JSON here; images
(`io.images`), subband EXR (`io.exr`), PLY (`io.ply`) and checkpoints (`io.checkpoint`) in their
modules, imported where used (OpenImageIO and torch stay out of a plain `wgs.io` import). Knows no
workspace or model."""

from .files import atomic_path, atomic_write_bytes, atomic_write_json, json_default, path_in, read_json

__all__ = ["atomic_path", "atomic_write_bytes", "atomic_write_json", "json_default", "path_in", "read_json"]
