"""`wgs view`: the model in the browser."""

from __future__ import annotations

from dataclasses import dataclass

import click

from ..errors import WgsError
from ..fields import option
from .main import workspace_option
from .options import ModelChoice, settings_options


@dataclass
class ViewSettings(ModelChoice):
    port: int = option(8765, "Port on 127.0.0.1 (0: any free one).", bounds=(0, 65535))
    no_browser: bool = option(False, "Print the address only; do not open a browser.")


@click.command()
@settings_options(ViewSettings)
@workspace_option
@click.pass_obj
def view(obj, stage, port, no_browser):
    """Look at the model in the browser: a WebGL splat viewer on 127.0.0.1 (Ctrl-C stops it)."""
    import time
    import webbrowser

    from ..progress import results
    from ..viewer import serving, site

    ws = obj.ws()
    if not ws.root.is_dir():
        raise WgsError("workspace folder not found", ws.root)
    files = site(ws, stage)
    with serving(files, port) as url:
        results.print(f"viewer: {url}  (report: {url}report.html)" if "/report.html" in files else f"viewer: {url}")
        results.print("Ctrl-C stops it")
        if not no_browser:
            webbrowser.open(url)
        while True:
            time.sleep(3600)
