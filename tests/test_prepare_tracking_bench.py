"""benchmarks/prepare_tracking.py's excerpt and scoring (issue 23's tracking round trip): an excerpt
holds the source's first frames of everything frame-indexed, and the score of a known offset from
the ground truth is that offset, in every group."""

import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))

from prepare_tracking import excerpt, score  # noqa: E402


def test_excerpt_cuts_every_frame_indexed_part(tiny_capture, tmp_path):
    from physavatar.capture import load_capture
    from physavatar.files import load_npz

    src = load_capture(tiny_capture)
    n = 3
    cut = load_capture(excerpt(Path(tiny_capture), tmp_path / "cut", n))
    assert cut.frames == src.frames[:n]
    np.testing.assert_array_equal(cut.body.rotations, src.body.rotations[:n])
    np.testing.assert_array_equal(cut.body.root_translation, src.body.root_translation[:n])
    gt_src = load_npz(src.ground_truth / "meshes.npz")["vertices"]
    np.testing.assert_array_equal(load_npz(cut.ground_truth / "meshes.npz")["vertices"], gt_src[:n])
    c = src.cameras[0].name
    np.testing.assert_array_equal(cut.image(c, src.frames[n - 1]), src.image(c, src.frames[n - 1]))
    assert not (tmp_path / "cut" / "images" / c / f"{src.frames[n]:06d}.png").exists()
    bare = excerpt(Path(tiny_capture), tmp_path / "bare", n, body=False, template=False)
    assert not (bare / "body.npz").exists() and not (bare / "template").exists()


def test_score_of_a_known_offset(tiny_capture, tmp_path):
    from physavatar.files import load_npz

    cap = excerpt(Path(tiny_capture), tmp_path / "cut", 3)
    gt = load_npz(cap / "ground_truth" / "meshes.npz")["vertices"].astype(np.float64)
    s = score(cap, gt)
    assert s["garment"]["mean_mm"] == pytest.approx(0.0, abs=1e-3) and s["body"]["mean_mm"] == pytest.approx(0.0, abs=1e-3)
    # 2 mm along x from frame 1 on: frame 0 scores 0, the others 2 mm, in every group
    off = gt.copy()
    off[1:, :, 0] += 0.002
    s = score(cap, off)
    assert s["garment"]["per_frame_mm"] == pytest.approx([0.0, 2.0, 2.0], abs=1e-3)
    for name, g in s["groups"].items():
        if g["vertices"]:
            assert g["mean_mm"] == pytest.approx(4.0 / 3, abs=1e-3), name
    assert sum(g["vertices"] for g in s["groups"].values()) == s["garment"]["vertices"]
    assert s["by_first_frame_error"]["<= 1 mm"]["growth_mm"] == pytest.approx(4.0 / 3, abs=1e-3)
