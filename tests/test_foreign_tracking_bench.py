"""benchmarks/foreign_tracking.py's fine-shape figures (session 37) against constructed deformations."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))

from foreign_tracking import detail_figures  # noqa: E402

from physavatar.stages.track.fit import smoothing_solver  # noqa: E402
from test_flow import _grid  # noqa: E402


def test_detail_figures_measure_the_share_of_the_folds_a_tracking_reproduced():
    """A sheet that folds (a bump at the scale of two edges) and moves rigidly: a tracking with
    the motion and half the bump has gain 0.5 and correlation 1; one with the motion alone gain 0;
    one with the bump's negative gain -1. The rigid motion is no fine shape (the low-pass keeps it
    exactly: (I + 3 L)^-1 of a constant is the constant)."""
    V, F = _grid(15, 0.4)
    low = smoothing_solver(len(V), F, 3.0)
    sel = np.ones(len(V), bool)
    r2 = np.square(V[:, 0] - 0.03) + np.square(V[:, 2] + 0.02)
    bump = np.zeros_like(V)
    bump[:, 1] = 0.01 * np.exp(-r2 / (2 * 0.03 ** 2))
    move = np.array([0.02, -0.01, 0.005])
    truth = V + move + bump
    for share, gain in ((0.5, 0.5), (0.0, 0.0), (-1.0, -1.0), (1.0, 1.0)):
        d = detail_figures(V, V + move + share * bump, V, truth, low, sel)
        assert abs(d["gain"] - gain) < 1e-9, (share, d)
        if share != 0:
            assert abs(abs(d["correlation"]) - 1) < 1e-9, d
            assert abs(d["tracked_mm"] - abs(share) * d["true_mm"]) < 1e-9
    assert detail_figures(V, V + move, V, V + move, low, sel)["true_mm"] < 1e-9
