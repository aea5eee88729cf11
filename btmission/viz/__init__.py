"""The live viewer: the mine, the fleet and every agent's behaviour tree in one browser page.

Pure parts (:mod:`~btmission.viz.mesh`, :mod:`~btmission.viz.feed`) take values and return
values; :mod:`~btmission.viz.scene` encodes the static scene as meshcat commands;
:mod:`~btmission.viz.server` serves the page (FastAPI on uvicorn, 127.0.0.1 by default) for a
live run (:class:`~btmission.viz.feed.LiveFeed`) or a finished one's log; :mod:`~btmission.viz.
export` writes the same page as one self-contained HTML file. Needs the ``viz`` extra
(``pip install 'btmission[viz]'``); ``import btmission`` never imports this package.
"""
