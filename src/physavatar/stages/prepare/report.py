"""The preparation report: ``prepare/report.md`` in the prepared capture, with pictures.

* ``masks.png``: every camera's first frame with its mask (given or computed) tinted;
* ``body.png``: the body drawn over every camera at the first, middle and last frames;
* ``segmentation.png``: the template's visible vertices over the first frame, body grey,
  garments in colour, boundary vertices red;
* ``distance.png``: the first-frame mesh's signed distance to the body, with the garment margin.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ...capture import Capture, save_png
from ...files import write_text_atomic

PALETTE = np.array([[170, 170, 170], [40, 140, 255], [60, 200, 90], [250, 200, 40], [200, 80, 220],
                    [40, 210, 210], [255, 140, 60], [120, 120, 255], [150, 220, 120], [230, 230, 230],
                    [90, 160, 160], [200, 160, 120], [160, 90, 60], [110, 200, 255], [255, 170, 200],
                    [140, 140, 60]], np.uint8)


def _u8(img: np.ndarray) -> np.ndarray:
    return (np.clip(img, 0, 1) * 255 + 0.5).astype(np.uint8)


def _dots(img: np.ndarray, uv: np.ndarray, colours: np.ndarray, r: int = 1) -> np.ndarray:
    import cv2

    out = img.copy()
    h, w = out.shape[:2]
    for (x, y), c in zip(np.round(uv).astype(int), colours):
        if 0 <= x < w and 0 <= y < h:
            cv2.circle(out, (int(x), int(y)), r, tuple(int(v) for v in c), -1)
    return out


def _sheet(images, names, path: Path) -> None:
    from ...render.sheet import contact_sheet

    save_png(path, contact_sheet(images, names))


def write_report(cap: Capture, root: Path, steps: dict, numbers: dict, progress=None,
                 warnings: list[str] | None = None) -> Path:
    """Write ``root/prepare/report.md`` and its pictures for the prepared capture ``cap``."""
    from .posing import pose_body
    from .segment import visible

    out = root / "prepare"
    out.mkdir(parents=True, exist_ok=True)
    f0 = cap.frames[0]
    imgs0 = {c.name: cap.image(c.name, f0) for c in cap.cameras}
    names = [c.name for c in cap.cameras]
    # masks
    tiles = []
    for c in cap.cameras:
        m = cap.mask(c.name, f0)[..., None]
        tiles.append(_u8(imgs0[c.name] * (0.35 + 0.65 * m) + np.array([0.0, 0.35, 0.0]) * m))
    _sheet(tiles, names, out / "masks.png")
    # body over every camera at three frames
    idx = sorted({0, len(cap.frames) // 2, len(cap.frames) - 1})
    model, posed = pose_body(cap.body, idx)
    tiles, labels = [], []
    step = max(1, len(model.faces) // 4000)
    for k, i in enumerate(idx):
        f = cap.frames[i]
        for c in cap.cameras:
            img = _u8(cap.image(c.name, f) * 0.7)
            tri = posed[k][model.faces[::step]].mean(1)
            uv, _ = c.project(tri)
            tiles.append(_dots(img, np.nan_to_num(uv, nan=-1), np.tile([[80, 255, 255]], (len(uv), 1)), 0))
            labels.append(f"{c.name} f{f}")
    _sheet(tiles, labels, out / "body.png")
    # segmentation and boundary
    t = cap.template
    from ...geometry.mesh import vertex_normals

    N = vertex_normals(t.vertices, t.faces)
    col = PALETTE[np.clip(t.labels, 0, len(PALETTE) - 1)].copy()
    col[t.boundary] = [255, 40, 40]
    tiles = []
    edge = float(np.median(np.linalg.norm(t.vertices[t.faces[:, 0]] - t.vertices[t.faces[:, 1]], axis=1)))
    for c in cap.cameras:
        vis, uv = visible(t.vertices, N, c, edge)
        order = np.argsort(t.boundary[vis])  # boundary drawn last
        sel = np.flatnonzero(vis)[order]
        tiles.append(_dots(_u8(imgs0[c.name] * 0.5), uv[sel], col[sel], 1))
    _sheet(tiles, names, out / "segmentation.png")
    figures = []
    if "_distance" in numbers:
        _distance_figure(numbers["_distance"], numbers, out / "distance.png")
        figures.append("distance.png")
    lines = ["# Preparation report", "", f"Capture `{cap.root}`: {len(cap.cameras)} cameras, {len(cap.frames)} frames.",
             ""]
    lines += [f"**Warning:** {w}" for w in warnings or []] + ([""] if warnings else [])
    lines += ["| step | what was done |", "| --- | --- |"]
    lines += [f"| {k} | {v} |" for k, v in steps.items()]
    tpl = numbers.get("template")
    if tpl:
        lines += ["", (f"Template: {tpl['vertices']} vertices, {tpl['faces']} faces, garments {tpl['garments']}, "
                       f"{tpl['boundary']} boundary vertices.")]
    if "masks" in numbers:
        lines += ["", "Masks per camera (background, threshold): " + ", ".join(
            f"{k}: {v['background']} {v['threshold']}" for k, v in numbers["masks"].items())]
        lines += ["", "Share of each camera's foreground outside the largest region (clutter), and of the image "
                  "that is foreground: " + ", ".join(f"{k}: {v.get('clutter', 0):.2f}, {v.get('foreground', 0):.2f}"
                                                    for k, v in numbers["masks"].items())]
    if numbers.get("boundary"):
        lines += ["", "Boundary per garment: " + "; ".join(
            f"garment {g}: {v}" for g, v in numbers["boundary"].items())]
    lines += ["", "## Pictures", "", "Masks (first frame):", "", "![masks](masks.png)", "",
              "The body over every camera (first, middle, last frame):", "", "![body](body.png)", "",
              "Segmentation (grey body, colours garments, red boundary):", "", "![segmentation](segmentation.png)"]
    for fig in figures:
        lines += ["", f"![{fig}]({fig})"]
    write_text_atomic(out / "report.md", "\n".join(lines) + "\n")
    return out / "report.md"


def _distance_figure(sd: np.ndarray, numbers: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from ...files import atomic_path

    fig, ax = plt.subplots(figsize=(6, 3.2), dpi=100)
    ax.hist(np.clip(sd * 100, -5, 20), bins=80, color="#4a8")
    ax.set_xlabel("signed distance of the first-frame mesh to the body [cm]")
    ax.set_ylabel("vertices")
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png")
    plt.close(fig)
