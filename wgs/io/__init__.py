"""The file layer under the workspace and the stages: atomic writes and JSON. Knows no workspace."""

from .files import atomic_path, atomic_write_bytes, atomic_write_json, json_default, path_in, read_json

__all__ = ["atomic_path", "atomic_write_bytes", "atomic_write_json", "json_default", "path_in", "read_json"]
