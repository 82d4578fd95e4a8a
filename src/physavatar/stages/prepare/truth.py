"""A synthetic capture's ground truth carried into the prepared capture.

Everything is linked as it is except ``ground_truth/meshes.npz``, whose per-vertex tracks
belong to the original template: they are re-expressed on the prepared template (the body part
is the same Anny mesh, copied vertex for vertex when the topologies agree; every other vertex
follows the closest point of the true surface of its own part in the first frame, by its
barycentric coordinates), so tracking on the prepared capture is scored against the truth.
"""

from __future__ import annotations

import os
import shutil
from pathlib import Path

import numpy as np

from ...files import load_npz, save_npz_atomic


def link_file(src: Path, dst: Path, copy: bool = False) -> None:
    """``dst`` as a hard link to ``src`` (a copy across file systems, or when ``copy``)."""
    dst.parent.mkdir(parents=True, exist_ok=True)
    if not copy:
        try:
            os.link(src, dst)
            return
        except OSError:
            pass
    shutil.copy2(src, dst)


def link_tree(src: Path, dst: Path, copy: bool = False, skip: tuple[str, ...] = ()) -> int:
    """Every file under ``src`` linked (or copied) to the same place under ``dst``; returns the count."""
    n = 0
    for p in sorted(Path(src).rglob("*")):
        rel = p.relative_to(src)
        if p.is_file() and str(rel) not in skip:
            link_file(p, Path(dst) / rel, copy)
            n += 1
    return n


def carry_truth(src: Path, dst: Path, vertices: np.ndarray, faces: np.ndarray, labels: np.ndarray) -> dict:
    """Link ``src`` (a ground_truth folder) to ``dst`` with meshes.npz on the prepared template
    (``vertices``, ``faces``, ``labels``); returns what was done."""
    from ...geometry.closest import MeshQuery

    link_tree(src, dst, skip=("meshes.npz",))
    if not (src / "meshes.npz").is_file():
        return {"meshes": "absent"}
    z = load_npz(src / "meshes.npz")
    Vt, Ft, Lt = z["vertices"].astype(np.float64), z["faces"].astype(np.int64), z["labels"].astype(np.int64)
    out = np.empty((len(Vt), len(vertices), 3))
    body_new, body_true = np.flatnonzero(labels == 0), np.flatnonzero(Lt == 0)
    done = np.zeros(len(vertices), bool)
    if len(body_new) == len(body_true) and np.abs(vertices[body_new] - Vt[0, body_true]).max() < 1e-3:
        out[:, body_new] = Vt[:, body_true]
        done[body_new] = True
    for part in (0, 1):  # body, garments: each from the true surface of the same part
        sel = np.flatnonzero(~done & ((labels > 0) == bool(part)))
        tf = Ft[((Lt[Ft] > 0) == bool(part)).all(1)]
        if not len(sel) or not len(tf):
            continue
        _, f, w, _ = MeshQuery(Vt[0], tf, spacing=0.02).closest(vertices[sel])
        out[:, sel] = np.einsum("nk,tnkd->tnd", w, Vt[:, tf[f]])
        done[sel] = True
    save_npz_atomic(dst / "meshes.npz", vertices=out.astype(np.float32), faces=faces,
                    labels=labels.astype(np.uint8), fps=z.get("fps", np.array(25.0)),
                    note=np.array("re-expressed on the prepared template (closest true surface points)"))
    return {"meshes": "re-expressed on the prepared template", "body_copied": bool(len(body_new) == len(body_true))}
