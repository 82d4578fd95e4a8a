"""The body fit's shape prior centre (stages/prepare/body_fit.py, ``shape_centre``) and the shape
errors of ``benchmarks/prepare_body_fit_variants.py`` (issue 23, session 34).

The prior is w Σ (phenotype - centre)²: checked against that formula, and the first phase is
checked to start from the centre (a few iterations on a one-frame capture leave the phenotypes
near their start).
"""

from __future__ import annotations

import dataclasses
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from physavatar.body.model import PHENOTYPES, BodyModel, BodyShape

BENCH = Path(__file__).resolve().parents[1] / "benchmarks"
CENTRE = (0.2, 0.35, 0.3, 0.7, 0.65, 0.35)  # the foreign benchmark's body


def test_shape_prior_is_centred_where_asked():
    from physavatar.stages.prepare.body_fit import BodyFitConfig, _Fitter

    p = torch.tensor([0.5, 0.4, 0.3, 0.6, 0.7, 0.1], dtype=torch.float64)
    w = 1e-3
    default = _Fitter(BodyFitConfig(keypoints="none", w_shape_prior=w), None, None, 25.0)
    assert float(default.shape_prior(p)) == pytest.approx(w * float(((p - 0.5) ** 2).sum()), rel=1e-12)
    cfg = BodyFitConfig(keypoints="none", w_shape_prior=w, shape_centre=CENTRE)
    fitter = _Fitter(cfg, None, None, 25.0)
    c = torch.tensor(CENTRE, dtype=torch.float64)
    assert float(fitter.shape_prior(c)) == 0.0
    assert float(fitter.shape_prior(p)) == pytest.approx(w * float(((p - c) ** 2).sum()), rel=1e-12)


def test_bad_shape_centre_is_one_clear_error():
    from physavatar.errors import PhysavatarError
    from physavatar.stages.prepare.body_fit import BodyFitConfig, _Fitter

    for bad in ((0.5, 0.5), (0.5, 0.5, 0.5, 0.5, 0.5, 1.5)):
        with pytest.raises(PhysavatarError, match="shape_centre must be 6 phenotypes"):
            _Fitter(BodyFitConfig(keypoints="none", shape_centre=bad), None, None, 25.0)


def _one_frame_capture(root: Path) -> Path:
    """One frame of the centre's body at rest, 4 views of 64 px (masks: its triangles filled)."""
    from PIL import Image, ImageDraw

    from physavatar.camera import ring_rig
    from physavatar.capture import frame_name, save_cameras, save_capture_meta, save_png

    body = BodyModel(BodyShape.from_array(np.array(CENTRE)), "collider")
    cams = ring_rig(4, 3.0, 1.0, (0, 0, 0.9), 64, 64, 40.0, n_elevated=1, elevated_height=2.6)
    save_capture_meta(root, fps=25.0, frames=[0])
    save_cameras(root, cams)
    for c in cams:
        uv, _ = c.project(body.rest_vertices)
        im = Image.new("L", (c.width, c.height), 0)
        draw = ImageDraw.Draw(im)
        for tri in uv[body.faces]:
            draw.polygon([(float(x), float(y)) for x, y in tri], fill=255)
        save_png(root / "masks" / c.name / f"{frame_name(0)}.png", np.asarray(im) > 127)
    return root


def test_first_phase_starts_from_the_centre(tmp_path):
    """A few iterations only (Adam's steps of 0.02 move a phenotype < 0.1): the first phase's
    phenotypes are those of its start, the centre when one is given, Anny's defaults otherwise."""
    from physavatar.progress import resolve
    from physavatar.stages.prepare.body_fit import BodyFitConfig, _Fitter
    from physavatar.stages.prepare.observations import _Observations

    root = _one_frame_capture(tmp_path / "cap")
    got = {}
    for name, centre in (("default", ()), ("centre", CENTRE)):
        cfg = BodyFitConfig(keypoints="none", shape_centre=centre, first_iterations=3, heading_iterations=1)
        prog = resolve(False)
        fitter = _Fitter(cfg, _Observations(root, cfg, prog), None, 25.0)
        with torch.set_grad_enabled(True), prog.task("t", total=7) as task:
            got[name] = fitter.first_frame(task)[2].numpy()
    assert np.abs(got["default"] - 0.5).max() < 0.1, got
    assert np.abs(got["centre"] - np.array(CENTRE)).max() < 0.1, got
    assert np.abs(got["centre"] - got["default"]).max() > 0.2


def test_shape_errors_of_the_benchmark():
    sys.path.insert(0, str(BENCH))
    try:
        from prepare_body_fit_variants import shape_errors
    finally:
        sys.path.remove(str(BENCH))
    same = shape_errors(CENTRE, CENTRE)
    assert same["rest_mean_mm"] == 0 and same["phenotype_rms"] == 0 and same["height_error_mm"] == 0
    other = np.array(CENTRE) + np.array([0.0, 0.0, 0.1, 0.0, 0.0, 0.0])
    e = shape_errors(CENTRE, other)
    assert all(abs(e["phenotype_error"][k] - (0.1 if k == "muscle" else 0.0)) < 1e-9 for k in PHENOTYPES)
    assert e["phenotype_rms"] == pytest.approx(0.1 / np.sqrt(6), abs=1e-4)
    # the rest bodies' distance, computed here from Anny directly
    a = BodyModel(BodyShape.from_array(np.array(CENTRE)), "collider").rest_vertices
    b = BodyModel(BodyShape.from_array(other), "collider").rest_vertices
    assert e["rest_mean_mm"] == pytest.approx(1000 * np.linalg.norm(a - b, axis=1).mean(), abs=0.01)
    assert e["rest_mean_mm"] > 0


def test_dataclass_field_types_parse_in_the_benchmark():
    sys.path.insert(0, str(BENCH))
    try:
        from prepare_body_fit_variants import config
    finally:
        sys.path.remove(str(BENCH))
    cfg = config({"shape_centre": "0.2/0.35/0.3/0.7/0.65/0.35", "w_shape_prior": "0"})
    assert cfg.shape_centre == CENTRE and cfg.w_shape_prior == 0.0
    assert dataclasses.replace(cfg, shape_centre=()).shape_centre == ()
