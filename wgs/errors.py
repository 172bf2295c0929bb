"""User-facing errors: one line naming the file and what is wrong; the CLI exits with status 2."""

from __future__ import annotations

from pathlib import Path


class WgsError(Exception):
    """A problem with the user's input or workspace (not a bug): printed as one line, exit 2."""

    def __init__(self, message: str, path: str | Path | None = None):
        # names that are not UTF-8 (surrogate escapes) are shown escaped, so the message always prints
        self.path = None if path is None else str(path).encode("utf-8", "backslashreplace").decode()
        self.message = message.encode("utf-8", "backslashreplace").decode()
        super().__init__(f"{self.path}: {self.message}" if self.path else self.message)


class InputError(WgsError):
    """Malformed scene, image, config or workspace file."""


class WorkspaceLocked(WgsError):
    """Another process holds the workspace lock."""
