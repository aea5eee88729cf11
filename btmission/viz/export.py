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
import re
from typing import Any

from btmission.viz.server import ViewerSource, meshcat_js, static_dir

_INLINE = {
    '<link rel="stylesheet" href="static/viewer.css">': "css",
    '<script src="static/meshcat.js"></script>': "meshcat",
    '<script src="static/viewer.js"></script>': "viewer",
    "/*BTM_CONFIG*/null": "config",
    "<!--BTM_TITLE-->": "title",
}


def _script_safe(text: str) -> str:
    """``text`` safe inside a ``<script>`` element (no ``</script>`` or ``<!--`` in it)."""
    return text.replace("</", "<\\/").replace("<!--", "<\\!--")


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
    parts = {
        "css": "<style>\n" + (static / "viewer.css").read_text(encoding="utf-8") + "\n</style>",
        "meshcat": "<script>\n" + _script_safe(meshcat_js().read_text(encoding="utf-8")) + "\n</script>",
        "viewer": "<script>\n" + _script_safe((static / "viewer.js").read_text(encoding="utf-8"))
        + "\n</script>",
        "config": _script_safe(json.dumps(config, separators=(",", ":"), allow_nan=False)),
        "title": _html_text(str(source.info.get("mission") or "btmission")),
    }
    template = (static / "index.html").read_text(encoding="utf-8")
    pattern = re.compile("|".join(re.escape(k) for k in _INLINE))
    return pattern.sub(lambda m: parts[_INLINE[m.group(0)]], template)  # one pass: inserted
    # text is never searched again


def _html_text(text: str) -> str:
    return text.replace("&", "&amp;").replace("<", "&lt;").replace(">", "&gt;")
