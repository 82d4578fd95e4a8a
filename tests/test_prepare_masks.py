"""prepare's masks step warns when background differencing without a plate is unreliable
(a cluttered room with people walking behind), records the warning, and stays quiet on a clean
scene (a plain backdrop) and with a plate."""

from __future__ import annotations

import logging

import numpy as np

from physavatar.camera import ring_rig
from physavatar.capture import load_unprepared, save_cameras, save_capture_meta, save_png
from physavatar.stages.prepare import PrepareConfig
from physavatar.stages.prepare.config import MaskConfig
from physavatar.stages.prepare.masks import camera_masks, mask_iou, reliability

H, W, T = 64, 48, 9
PALETTE = np.array([[0.2, 0.3, 0.6], [0.5, 0.5, 0.5], [0.8, 0.75, 0.7], [0.1, 0.1, 0.1], [0.6, 0.2, 0.2],
                    [0.3, 0.6, 0.3]])


def _scene(seed: int, passers: bool, backdrop: bool = False) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """Frames and the person's true masks: a person-sized block moving across a room (a patchwork
    of six colours) or a plain dark backdrop; with ``passers``, two smaller blocks of other colours
    (people walking behind) cross the room in the frames' other rows."""
    rng = np.random.default_rng(seed)
    if backdrop:
        room = np.full((H, W, 3), 0.05) + rng.normal(0, 0.005, (H, W, 3))
    else:
        tiles = rng.integers(0, len(PALETTE), (H // 4, W // 4))
        room = PALETTE[np.kron(tiles, np.ones((4, 4), int))] + rng.normal(0, 0.02, (H, W, 3))
    frames, truth = [], []
    for t in range(T):
        im = room.copy()
        m = np.zeros((H, W), bool)
        m[22:52, 4 + 4 * t:14 + 4 * t] = True
        im[m] = [0.85, 0.6, 0.5]
        if passers:
            im[2:14, (40 - 5 * t) % W:(40 - 5 * t) % W + 8] = [0.95, 0.95, 0.2]
            im[54:63, (3 * t) % W:(3 * t) % W + 10] = [0.1, 0.9, 0.9]
        frames.append(np.clip(im, 0, 1))
        truth.append(m)
    return frames, truth


def _capture(root, passers: bool, backdrop: bool = False):
    cams = ring_rig(2, 2.5, 1.0, (0, 0, 1.0), W, H, 40.0)
    save_cameras(root, cams)
    save_capture_meta(root, fps=30.0, frames=list(range(T)))
    truth = {}
    for i, c in enumerate(cams):
        frames, truth[c.name] = _scene(i, passers, backdrop)
        for t, im in enumerate(frames):
            save_png(root / "images" / c.name / f"{t:06d}.png", im)
    return root, truth


def test_reliability_measures_one_region():
    one = np.zeros((20, 20), bool)
    one[5:15, 5:10] = True  # 50 px
    two = one.copy()
    two[0:2, 15:20] = True  # 10 px elsewhere
    assert reliability([one]) == {"clutter": 0.0, "foreground": 0.125}
    assert reliability([one, two])["clutter"] == round(0.5 * 10 / 60, 4)


def test_cluttered_room_without_plate_is_warned_and_recorded(tmp_path, caplog):
    """People walking behind make differencing's masks several regions: one warning line naming
    the cameras and what to do, in the step's record; the clean backdrop and a plate give none."""
    from physavatar.stages.prepare.stage import _masks

    src, truth = _capture(tmp_path / "room", passers=True)
    raw = load_unprepared(src)
    (tmp_path / "out").mkdir()
    with caplog.at_level(logging.WARNING, logger="physavatar.progress"):
        step, numbers, warning = _masks(src, tmp_path / "out", raw, PrepareConfig(), None)
    assert step == "computed: background differencing (temporal median)"
    assert warning is not None and "2 of 2 cameras" in warning
    for what in ("MediaPipe", "physavatar[keypoints]", "masks/", "background/"):
        assert what in warning
    lines = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert len(lines) == 1 and warning in lines[0] and str(src) in lines[0]
    for name, n in numbers.items():
        assert n["clutter"] > 0.25, n  # the passers-by are about a third of the foreground
        m = [np.asarray(a) > 0 for a in _read(tmp_path / "out", name)]
        assert np.mean([mask_iou(a, b) for a, b in zip(m, truth[name])]) < 0.8  # they are in the masks

    # a plain backdrop and the person alone: no warning, one region
    src, _ = _capture(tmp_path / "backdrop", passers=False, backdrop=True)
    (tmp_path / "out2").mkdir()
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="physavatar.progress"):
        _, numbers, warning = _masks(src, tmp_path / "out2", load_unprepared(src), PrepareConfig(), None)
    assert warning is None and not caplog.records
    assert all(n["clutter"] == 0.0 for n in numbers.values())


def test_plate_is_not_warned(tmp_path):
    """With a plate of the room the passers-by are still foreground, but the user gave what
    differencing needs: the reliability is recorded, no warning."""
    from physavatar.stages.prepare.masks import unreliable_warning

    frames, _ = _scene(0, passers=True)
    paths = []
    for t, im in enumerate(frames):
        paths.append(tmp_path / f"{t:06d}.png")
        save_png(paths[-1], im)
    ms, info = camera_masks(paths, MaskConfig())
    info |= reliability(ms)
    assert unreliable_warning({"a": info}, MaskConfig()) is not None
    assert unreliable_warning({"a": info | {"background": "plate"}}, MaskConfig()) is None


def _read(root, cam):
    from physavatar.capture import _read_png

    return [_read_png(root / "masks" / cam / f"{t:06d}.png", "L") for t in range(T)]
