"""One self-contained HTML file of a run: meshcat's static export plus the viewer's panels.

meshcat's own static export inlines its viewer bundle and feeds the scene's packed commands to
``viewer.handle_command_bytearray`` from base64 text. :func:`static_html` does the same with the
whole viewer page: its CSS, meshcat's bundle and ``viewer.js`` inlined, and the scene and the
run's records embedded as JSON (``window.BTM_CONFIG``), so the file opens offline, in any
browser, with play/pause and the time slider working. Only a LiDAR scan (computed by the
server) is unavailable.
"""

from __future__ import annotations

import base64
import json
from pathlib import Path
from typing import Any

from btmission.viz.server import ViewerSource, meshcat_js, page_html, script_safe, static_dir


def static_html(source: ViewerSource) -> str:
    """The page of ``source`` (a finished run's :func:`~btmission.viz.server.log_source`) as one
    HTML document (module docstring)."""
    scene = source.scene()
    records, _, _, _ = source.feed.read(0)
    config: dict[str, Any] = {
        "embedded": True,
        "info": source.full_info(),
        "scene": base64.b64encode(scene.packed()).decode("ascii") if scene is not None else "",
        "records": records,
    }
    static = static_dir()

    def script(path: Path) -> str:
        return "<script>\n" + script_safe(path.read_text(encoding="utf-8")) + "\n</script>"

    inline = {
        "css": "<style>\n" + (static / "viewer.css").read_text(encoding="utf-8") + "\n</style>",
        "meshcat": script(meshcat_js()),
        "viewer": script(static / "viewer.js"),
    }
    config_json = json.dumps(config, separators=(",", ":"), allow_nan=False)  # (a big file)
    return page_html(config_json, str(source.info.get("mission") or "btmission"), inline)
