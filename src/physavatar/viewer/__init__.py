"""``physavatar view``: a local web viewer (viser) for every folder physavatar reads or writes.

:func:`load_scene` recognizes a folder (``scene.py``: capture, run, track, simulate, animate,
avatar) and reads it through the ``data/`` objects into layers, cameras and panels;
:class:`Viewer` (``server.py``) serves it on 127.0.0.1 with a time slider, play/pause, layer
toggles, error colouring against ground truth, camera views and JSON panels, and saves a
self-contained HTML file (:meth:`Viewer.save_html`). docs/viewer.md has the details.
"""

from __future__ import annotations

from .scene import Layer, Scene, ViewCamera, detect, load_scene  # noqa: F401
from .server import Viewer, check_port, save_view  # noqa: F401
