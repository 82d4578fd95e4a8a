"""Frame 1 of a tracking run against synthetic truth: held at the template by default, and what
the frame-1 vertex fit (``FitConfig.first_vertex_iters``, off by default; issue 23, session 32)
does to a template that is off.

The capture of tests/test_track.py (Anny walking, four 64-px cameras, noisy per-vertex colours,
true vertices known) with its template pushed 2 cm out along the vertex normals (half a pixel at
the body). Held, frame 1's error is the push to the micrometre. Fitted (the later frames' loss,
regularisers and step sizes on frame 1's images, after the colour fit on the pushed template),
the vertices move but do not come back: the colours fitted on the pushed surface leave the
photometric loss no pull back towards the truth (measured 20.0 -> 22.6 mm; on the demo's prepared capture 3.11
-> 5.31 mm, on its original 0 -> 2.04 mm: docs/prepare.md, session 32). The test pins that
finding: if a change makes the frame-1 fit pull the template back, the default should be revisited.
"""

from __future__ import annotations

import json
import shutil
from dataclasses import replace

import numpy as np
import pytest
import trimesh

from physavatar.capture import Template, load_capture
from physavatar.errors import PhysavatarError
from physavatar.metrics import vertex_error_mm
from physavatar.stages.track import track
from test_track import FAST, body_capture  # noqa: F401  (the module's capture fixture)

PUSH = 0.02  # m, along the vertex normals


def _pushed_capture(root, tmp_path):
    dst = tmp_path / "pushed"
    shutil.copytree(root, dst)
    t = load_capture(dst).template
    n = trimesh.Trimesh(t.vertices, t.faces, process=False).vertex_normals
    Template(t.vertices + PUSH * n, t.faces, t.labels, t.boundary).save(dst / "template" / "mesh.ply")
    return dst


def test_frame_one_is_held_and_its_vertex_fit_does_not_undo_a_pushed_template(body_capture, tmp_path):  # noqa: F811
    root, gt = body_capture
    pushed = _pushed_capture(root, tmp_path)
    one = replace(FAST, n_frames=1)
    held = track(pushed, tmp_path / "held", one, progress=False)
    e_held = vertex_error_mm(held.vertices[:1], gt[:1])["mean_mm"][0]
    assert abs(e_held - 1e3 * PUSH) < 0.01, e_held  # frame 1 is the template
    fit_cfg = replace(one, fit=replace(one.fit, first_vertex_iters=40))
    fitted = track(pushed, tmp_path / "fitted", fit_cfg, progress=False)
    moved = np.linalg.norm(fitted.vertices[0] - held.vertices[0], axis=1).mean() * 1e3
    e_fit = vertex_error_mm(fitted.vertices[:1], gt[:1])["mean_mm"][0]
    assert moved > 1.0, moved  # the vertices were fitted ...
    assert e_fit > 0.8 * e_held, (e_held, e_fit)  # ... and did not come back (measured 22.6 mm)
    # a run folder written before the setting existed resumes (it held frame 1)
    cfg = json.loads((tmp_path / "held" / "config.json").read_text())
    del cfg["fit"]["first_vertex_iters"]
    (tmp_path / "held" / "config.json").write_text(json.dumps(cfg))
    assert track(pushed, tmp_path / "held", one, progress=False).computed == []
    with pytest.raises(PhysavatarError, match="first_vertex_iters"):
        track(pushed, tmp_path / "bad", replace(one, fit=replace(one.fit, first_vertex_iters=-1)), progress=False)
