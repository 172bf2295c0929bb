"""pycolmap for the scene layer. Its glog installs a native handler on import that answers SIGTERM
with a stack trace; the CLI's stop handlers (`resume.install_stop_handlers`) are put back after it."""

import pycolmap

from ..resume import restore_stop_handlers

restore_stop_handlers()

__all__ = ["pycolmap"]
