"""Checks of a capture that need its pieces together: does the template, projected by each
camera, cover that camera's mask?

A camera that is wrong by half a pixel (a principal point in another pixel-centre convention),
stored camera-to-world instead of world-to-camera, or in OpenGL axes still passes every check of
the files one by one, and then costs the whole pipeline accuracy (mask IoU 0.957 instead of 0.993
for half a pixel). ``physavatar inspect`` calls :func:`alignment_problems`: the template's
silhouette, rasterised exactly at the pixel centres (integer coordinates, as in
docs/capture-format.md), is compared with the first frame's
mask as given and shifted by ±½ pixel, and with the other conventions' cameras; a camera
that fits clearly better moved says by how much and what it likely is.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from .camera import Camera

SHIFTS = (-0.5, 0.0, 0.5)
GAIN = 0.005  # IoU a shifted camera must gain (and halve the mismatch) to count as misplaced
LOW_IOU = 0.5  # below: the template does not line up with the mask at all


def _cover(tri: np.ndarray, W: int, H: int) -> np.ndarray:
    """[H, W] bool: grid points (integer coordinates) inside any of the triangles ``tri`` [T, 3, 2]
    (exact, both orientations; points on an edge count as inside)."""
    img = np.zeros(H * W, bool)
    lo = np.maximum(np.ceil(tri.min(axis=1)).astype(np.int64), 0)
    hi = np.minimum(np.floor(tri.max(axis=1)).astype(np.int64), [W - 1, H - 1])
    size = np.max(hi - lo + 1, axis=1)
    keep = size > 0
    tri, lo, size = tri[keep], lo[keep], size[keep]
    side = 2 ** np.ceil(np.log2(size)).astype(np.int64)  # candidate square per triangle, ≤ 4× its box
    for k in np.unique(side):
        sel = np.flatnonzero(side == k)
        gx, gy = np.meshgrid(np.arange(k), np.arange(k))
        for chunk in np.array_split(sel, len(sel) * k * k // 1_000_000 + 1):
            px = lo[chunk, 0, None] + gx.ravel()[None]  # [n, k²]
            py = lo[chunk, 1, None] + gy.ravel()[None]
            a, b, c = (tri[chunk, i] for i in range(3))
            e = [(q[:, None, 0] - p[:, None, 0]) * (py - p[:, None, 1]) - (q[:, None, 1] - p[:, None, 1]) * (px - p[:, None, 0])
                 for p, q in ((a, b), (b, c), (c, a))]
            inside = ((e[0] >= 0) & (e[1] >= 0) & (e[2] >= 0)) | ((e[0] <= 0) & (e[1] <= 0) & (e[2] <= 0))
            inside &= (px < W) & (py < H)
            img[(py * W + px)[inside]] = True
    return img.reshape(H, W)


def _projected(camera: Camera, vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    uv, depth = camera.project(np.asarray(vertices, np.float64))
    return uv[faces[(depth[faces] > 1e-6).all(axis=1)]]  # [T, 3, 2], triangles in front


def silhouette(camera: Camera, vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """[H, W] bool: pixels whose centre (integer coordinates) lies inside a projected triangle in
    front of the camera. Exact coverage (no conservative edge pixels), so half a pixel shows."""
    return _cover(_projected(camera, vertices, faces), camera.width, camera.height)


def shifted_silhouettes(camera: Camera, vertices: np.ndarray, faces: np.ndarray) -> dict:
    """{(dx, dy): silhouette with the projection moved by (dx, dy)} for dx, dy in :data:`SHIFTS`,
    from one rasterisation on the half-pixel grid (sample j at x = j/2 − ½)."""
    W, H = camera.width, camera.height
    fine = _cover((_projected(camera, vertices, faces) + 0.5) * 2.0, 2 * W + 1, 2 * H + 1)
    # the silhouette moved by d, at pixel x, is the coverage at x − d: fine index 2(x − d) + 1
    return {(dx, dy): fine[int(1 - 2 * dy)::2, int(1 - 2 * dx)::2][:H, :W] for dx in SHIFTS for dy in SHIFTS}


def iou(a: np.ndarray, b: np.ndarray) -> float:
    union = np.logical_or(a, b).sum()
    return float(np.logical_and(a, b).sum() / union) if union else 1.0


def _conventions(camera: Camera) -> dict[str, Camera]:
    """The camera as other tools would have meant its matrix: camera-to-world, OpenGL axes."""
    flip = np.diag([1.0, -1.0, -1.0, 1.0])
    out = {}
    for name, w2c in (("camera-to-world (inverted)", np.linalg.inv(camera.w2c)),
                      ("OpenGL axes (y up, z back)", flip @ camera.w2c),
                      ("camera-to-world in OpenGL axes", flip @ np.linalg.inv(camera.w2c))):
        out[name] = replace(camera, w2c=w2c)
    return out


def camera_alignment(camera: Camera, mask: np.ndarray, vertices: np.ndarray, faces: np.ndarray, *,
                     conventions: bool = False) -> dict:
    """IoU of the template's silhouette with ``mask`` (bool) as given and at every shift in
    :data:`SHIFTS`², the best shift; with ``conventions`` (or a low IoU) also the IoU of the
    camera read in the other conventions."""
    shifted = {d: iou(s, mask) for d, s in shifted_silhouettes(camera, vertices, faces).items()}
    best = max(shifted, key=shifted.get)
    out = {"iou": shifted[(0.0, 0.0)], "best_shift": best, "best_shift_iou": shifted[best]}
    if conventions or out["iou"] < LOW_IOU:
        out["conventions"] = {name: iou(silhouette(c, vertices, faces), mask) for name, c in _conventions(camera).items()}
    return out


def alignment_problems(cap) -> list[tuple[object, str]]:
    """(path, problem) for every camera whose first-frame mask the template does not cover as it
    should (see the module docstring); none when the capture has no masks."""
    if not cap.has_masks:
        return []
    t = cap.template
    f = cap.frames[0]
    problems = []
    for cam in cap.cameras:
        mask = cap.mask(cam.name, f) > 0.5
        a = camera_alignment(cam, mask, t.vertices, t.faces)
        path = cap.root / "cameras.json"
        conv, conv_iou = max(a.get("conventions", {"": 0.0}).items(), key=lambda kv: kv[1])
        if a["iou"] < LOW_IOU and conv_iou > a["iou"] + 0.2:
            problems.append((path, f"camera {cam.name!r}: the template covers its mask with IoU {a['iou']:.2f}, "
                                   f"{conv_iou:.2f} if its matrix were {conv}: convert it to world-to-camera "
                                   "OpenCV axes (docs/capture-format.md)"))
        elif a["iou"] < LOW_IOU:
            problems.append((cap.mask_path(cam.name, f), f"camera {cam.name!r}: the template covers this mask with "
                                                         f"IoU {a['iou']:.2f} only: wrong camera, frame or template"))
        elif a["best_shift_iou"] - a["iou"] > GAIN and 1 - a["iou"] > 2 * (1 - a["best_shift_iou"]):
            dx, dy = a["best_shift"]
            problems.append((path, f"camera {cam.name!r}: the template fits its mask better moved by ({dx:+g}, {dy:+g}) px "
                                   f"(IoU {a['best_shift_iou']:.3f} against {a['iou']:.3f}): is the principal point in "
                                   "another pixel convention? K must put pixel centres at integer coordinates "
                                   "(docs/capture-format.md)"))
    return problems
