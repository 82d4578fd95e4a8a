"""Foreground masks when a capture has none: background differencing, offline (OpenCV).

Where the background comes from, per camera:

* a **background plate**, ``background/<camera>.png`` (or ``.jpg``) in the capture: a picture
  from the same camera without the person (docs/prepare.md);
* otherwise the **temporal median** of the camera's frames (the person moves, so each pixel
  shows the background in most frames), re-estimated ``refine`` times from the pixels the
  previous masks call background. A person who stays in place leaves a ghost in the median;
  where the background's colours are those of the image border (a studio wall, a backdrop: at
  least ``border_share`` of the median image is within the threshold of the border's colours,
  k-means clusters of the border pixels), a pixel must also be close to a border colour to be
  background, which removes the ghost.

Each frame's colour distance to its background is thresholded (Otsu's threshold on the
camera's distance histogram, or a fixed one), then cleaned with OpenCV morphology: an opening
removes speckle, a closing joins cracks, regions smaller than ``min_area`` of the image are
dropped and holes inside the person are filled.

Without a plate, differencing is unreliable in a cluttered or changing scene (people walking
behind, a person who stays in place and leaves a ghost in the median). Each camera's masks are
measured for that (:func:`reliability`): the share of the foreground outside each frame's
largest region (one person is one region: the synthetic captures 0.00, the Pose2Sim lab clip
0.40-0.54) and the share of the image that is foreground. Past ``max_clutter`` or
``max_foreground`` :func:`estimate_masks` logs one warning line saying what to do and returns it
(``prepare`` records it in prepare.json, capture.json and the report).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ...capture import _read_png, frame_name
from ...errors import PhysavatarError
from .config import MaskConfig

MAX_BACKGROUND_FRAMES = 32  # frames the median is taken over (evenly spread)


def plate_path(root: Path, cam: str) -> Path | None:
    """The camera's background plate in the capture, if any."""
    for ext in (".png", ".jpg", ".jpeg"):
        p = Path(root) / "background" / f"{cam}{ext}"
        if p.is_file():
            return p
    return None


def _read_rgb(path: Path) -> np.ndarray:
    return _read_png(path, "RGB")


def _disk(r: int):
    import cv2

    return cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))


def _distance(img: np.ndarray, bg: np.ndarray) -> np.ndarray:
    """[H, W] colour distance in [0, 1] (RGB Euclidean / sqrt 3)."""
    return np.sqrt(((img - bg) ** 2).sum(-1) / 3.0)


def _otsu(values: np.ndarray) -> float:
    import cv2

    v = np.clip(values.ravel() * 255.0, 0, 255).astype(np.uint8)[None]
    t, _ = cv2.threshold(v, 0, 255, cv2.THRESH_BINARY + cv2.THRESH_OTSU)
    return float(t) / 255.0


def clean_mask(raw: np.ndarray, cfg: MaskConfig) -> np.ndarray:
    """[H, W] bool: opened, closed, small regions dropped, holes filled."""
    import cv2

    m = raw.astype(np.uint8)
    if cfg.open_px > 0:
        m = cv2.morphologyEx(m, cv2.MORPH_OPEN, _disk(cfg.open_px))
    if cfg.close_px > 0:
        m = cv2.morphologyEx(m, cv2.MORPH_CLOSE, _disk(cfg.close_px))
    n, lab, stats, _ = cv2.connectedComponentsWithStats(m, connectivity=8)
    keep = np.zeros(n, bool)
    keep[1:] = stats[1:, cv2.CC_STAT_AREA] >= cfg.min_area * m.size
    m = keep[lab].astype(np.uint8)
    # fill holes: what the border cannot reach through the background is inside the person
    h, w = m.shape
    flood = np.zeros((h + 2, w + 2), np.uint8)
    flood[1:-1, 1:-1] = m
    ff = flood.copy()
    cv2.floodFill(ff, np.zeros((h + 4, w + 4), np.uint8), (0, 0), 1)
    holes = ff[1:-1, 1:-1] == 0
    return (m > 0) | holes


def _background(stack: np.ndarray, masks: np.ndarray | None) -> np.ndarray:
    """[H, W, 3] per-pixel median of ``stack`` [T, H, W, 3] over the frames where ``masks`` [T, H, W]
    says background (all frames where no frame does)."""
    if masks is None:
        return np.median(stack, axis=0)
    data = np.where(masks[..., None], np.nan, stack)
    with np.errstate(all="ignore"):
        import warnings

        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            bg = np.nanmedian(data, axis=0)
    fallback = np.median(stack, axis=0)
    return np.where(np.isnan(bg), fallback, bg)


def camera_masks(images: list[Path], cfg: MaskConfig, plate: Path | None = None) -> tuple[list[np.ndarray], dict]:
    """Masks ([H, W] bool) of one camera's frames (``images``, in order), and what was used
    (``background``: plate or median, ``threshold``)."""
    idx = np.unique(np.linspace(0, len(images) - 1, min(len(images), MAX_BACKGROUND_FRAMES)).round().astype(int))
    stack = np.stack([_read_rgb(images[i]) for i in idx])
    if plate is not None:
        bg = _read_rgb(plate)
        if bg.shape != stack.shape[1:]:
            raise PhysavatarError(plate, f"background plate is {bg.shape[1]}x{bg.shape[0]} but the camera's images "
                                  f"are {stack.shape[2]}x{stack.shape[1]}")
    else:
        bg = _background(stack, None)
    rounds = 0 if plate is not None else max(cfg.refine, 0)
    thr = cfg.threshold
    border = None
    if plate is None:
        centres, spread = _border_colours(stack)
        d_bg = _colour_distance(bg, centres)
        # the border's own scatter about its colours is the background's noise
        t_b = cfg.threshold or max(3.0 * spread, cfg.min_threshold)
        if t_b <= cfg.border_max_threshold and (d_bg < t_b).mean() >= cfg.border_share:
            border = (centres, t_b)
            rounds = 0  # the border colours decide: the median is not refined
    for r in range(rounds + 1):
        dist = np.stack([_distance(im, bg) for im in stack])
        thr = cfg.threshold or max(_otsu(dist), cfg.min_threshold)
        if r == rounds:
            break
        fg = np.stack([clean_mask(_raw(im, d, thr, border), cfg) for im, d in zip(stack, dist)])
        import cv2

        grow = _disk(max(2, cfg.close_px))
        fg = np.stack([cv2.dilate(m.astype(np.uint8), grow) > 0 for m in fg])
        bg = _background(stack, fg)
    out = []
    for i, p in enumerate(images):
        im = _read_rgb(p)
        out.append(clean_mask(_raw(im, _distance(im, bg), thr, border), cfg))
    source = "plate" if plate is not None else ("border colours" if border else "temporal median")
    return out, {"background": source, "threshold": round(border[1] if border else thr, 4),
                 "background_image": bg}


def _raw(im: np.ndarray, dist: np.ndarray, thr: float, border) -> np.ndarray:
    if border is not None:  # the background has the border's colours: they decide
        centres, thr = border
        dist = _colour_distance(im, centres)
    return _half_coverage(dist, thr)


def _half_coverage(dist: np.ndarray, thr: float, r: int = 2) -> np.ndarray:
    """Foreground pixels: farther than ``thr`` from the background and at least half as far as
    the farthest pixel within ``r`` (an edge pixel mixes person and background in proportion to
    its coverage, so this keeps the pixels more than half covered, as a true mask at 0.5 does)."""
    import cv2

    peak = cv2.dilate(dist.astype(np.float32), _disk(r))
    return (dist > thr) & (dist >= 0.5 * peak)


def _border_colours(stack: np.ndarray, k: int = 6, width: int = 2) -> np.ndarray:
    """[k, 3] k-means centres of the colours on the frames' image border, and the 95th percentile
    of the border pixels' distance to their centre."""
    import cv2

    s = stack
    px = np.concatenate([s[:, :width].reshape(-1, 3), s[:, -width:].reshape(-1, 3),
                         s[:, :, :width].reshape(-1, 3), s[:, :, -width:].reshape(-1, 3)]).astype(np.float32)
    k = min(k, len(px))
    crit = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 20, 1e-3)
    cv2.setRNGSeed(0)
    _, _, centres = cv2.kmeans(px, k, None, crit, 2, cv2.KMEANS_PP_CENTERS)
    centres = centres.astype(np.float32)
    d = np.sqrt(((px[:, None] - centres[None]) ** 2).sum(-1) / 3.0).min(1)
    return centres, float(np.percentile(d, 95))


def _colour_distance(img: np.ndarray, centres: np.ndarray) -> np.ndarray:
    """[H, W] distance of each pixel's colour to the nearest of ``centres`` (as :func:`_distance`)."""
    d = np.full(img.shape[:2], np.inf, np.float32)
    for c in centres:
        d = np.minimum(d, _distance(img, c[None, None]))
    return d


def reliability(masks: list[np.ndarray]) -> dict:
    """How much a camera's masks look like one person: ``clutter``, the mean share of each
    frame's foreground outside its largest connected region, and ``foreground``, the mean share
    of the image that is foreground."""
    import cv2

    clutter, fg = [], []
    for m in masks:
        _, _, stats, _ = cv2.connectedComponentsWithStats(np.asarray(m).astype(np.uint8), connectivity=8)
        a = stats[1:, cv2.CC_STAT_AREA]
        clutter.append(1.0 - a.max() / a.sum() if a.sum() else 0.0)
        fg.append(float(np.asarray(m).mean()))
    return {"clutter": round(float(np.mean(clutter)), 4), "foreground": round(float(np.mean(fg)), 4)}


def unreliable_warning(info: dict, cfg: MaskConfig) -> str | None:
    """One line when the masks differencing computed without background plates look unreliable
    (``info``: :func:`estimate_masks`'s per camera record), else None."""
    bad = {k: v for k, v in info.items() if v["background"] not in ("plate", "mediapipe person segmentation")
           and (v["clutter"] > cfg.max_clutter or v["foreground"] > cfg.max_foreground)}
    if not bad:
        return None
    what = []
    for key, limit, label in (("clutter", cfg.max_clutter, "share of the foreground outside its largest region"),
                              ("foreground", cfg.max_foreground, "share of the image foreground")):
        over = [f"{k} {100 * v[key]:.0f} %" for k, v in bad.items() if v[key] > limit]
        if over:
            what.append(f"{label}: " + ", ".join(over))
    return (f"masks by background differencing without a background plate look unreliable in {len(bad)} of "
            f"{len(info)} cameras ({'; '.join(what)}: a cluttered or changing background): install the MediaPipe "
            "extra (pip install 'physavatar[keypoints]'), give masks (masks/<camera>/<frame>.png) or background "
            "plates (background/<camera>.png)")


def segmentation_masks(images: list[Path], cfg: MaskConfig) -> tuple[list[np.ndarray], dict]:
    """Masks of one camera's frames from MediaPipe's person segmentation (the Pose solution's
    segmentation output, whose model ships inside the wheel: nothing is downloaded), its
    probability above ``segmentation_threshold``, cleaned like the differencing's masks."""
    import mediapipe as mp

    out = []
    with mp.solutions.pose.Pose(static_image_mode=True, model_complexity=1, enable_segmentation=True,
                                min_detection_confidence=0.3) as pose:
        for p in images:
            im = _read_rgb(p)
            if im.dtype != np.uint8:
                im = (np.clip(im, 0, 1) * 255 + 0.5).astype(np.uint8)
            prob = pose.process(np.ascontiguousarray(im[..., :3])).segmentation_mask
            if prob is None:
                prob = np.zeros(im.shape[:2])
            out.append(clean_mask(np.asarray(prob) > cfg.segmentation_threshold, cfg))
    return out, {"background": "mediapipe person segmentation", "threshold": cfg.segmentation_threshold}


def mask_method(root: Path, cameras: list, cfg: MaskConfig) -> str:
    """``difference`` or ``mediapipe`` for the capture at ``root`` (``cfg.method`` resolved: auto is
    difference when every camera has a background plate, else mediapipe when it is installed)."""
    if cfg.method != "auto":
        if cfg.method == "mediapipe":
            from .keypoints import mediapipe_available

            why = mediapipe_available()
            if why is not None:
                raise PhysavatarError(Path(root), f"--mask-method mediapipe: {why}")
        return cfg.method
    if all(plate_path(root, c.name) is not None for c in cameras):
        return "difference"
    from .keypoints import mediapipe_available

    return "mediapipe" if mediapipe_available() is None else "difference"


def estimate_masks(root: Path, cameras: list, frames: list[int], cfg: MaskConfig, progress=None
                   ) -> tuple[dict[str, list[np.ndarray]], dict, str | None]:
    """Masks of every camera and frame of the capture at ``root``: {camera: [T × [H, W] bool]}, per
    camera what was used (background source, threshold) and how reliable the masks look
    (:func:`reliability`), and the warning (logged here) when differencing looks unreliable."""
    import logging

    from ...progress import resolve

    method = mask_method(root, cameras, cfg)
    out, info = {}, {}
    with resolve(progress).task("prepare: masks", total=len(cameras)) as task:
        for c in cameras:
            paths = [Path(root) / "images" / c.name / f"{frame_name(f)}.png" for f in frames]
            if method == "mediapipe":
                out[c.name], info[c.name] = segmentation_masks(paths, cfg)
            else:
                out[c.name], info[c.name] = camera_masks(paths, cfg, plate_path(root, c.name))
            info[c.name].update(reliability(out[c.name]))
            task.advance(camera=c.name, threshold=info[c.name]["threshold"])
    warning = unreliable_warning(info, cfg)
    if warning is not None:
        logging.getLogger("physavatar.progress").warning("%s: %s", root, warning)
    return out, info, warning


def mask_iou(pred: np.ndarray, true: np.ndarray) -> float:
    """Intersection over union of two masks (``true`` > 0.5 is foreground)."""
    p, t = np.asarray(pred) > 0.5, np.asarray(true) > 0.5
    union = (p | t).sum()
    return float((p & t).sum() / union) if union else 1.0
