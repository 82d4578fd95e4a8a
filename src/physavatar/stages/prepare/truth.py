"""A synthetic capture's ground truth carried into the prepared capture.

Everything is linked as it is except ``ground_truth/meshes.npz`` and
``ground_truth/heldout/meshes.npz`` (the held-out motion's true meshes), whose per-vertex tracks
belong to the original template: they are re-expressed on the prepared template (the body part
is the same Anny mesh, copied vertex for vertex when the topologies agree; every other vertex
follows the closest point of the true surface of its own part in the first frame, by its
barycentric coordinates), so tracking and the held-out motion of the prepared capture are scored
against the truth (at the prepared garment's points: a garment part the preparation missed is
not scored).
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
    """Link ``src`` (a ground_truth folder) to ``dst`` with meshes.npz and heldout/meshes.npz on
    the prepared template (``vertices``, ``faces``, ``labels``); returns what was done."""
    from ...geometry.closest import MeshQuery

    meshes = ("meshes.npz", "heldout/meshes.npz")
    link_tree(src, dst, skip=meshes)
    if not (src / "meshes.npz").is_file():
        for m in meshes[1:]:
            if (src / m).is_file():
                link_file(src / m, dst / m)
        return {"meshes": "absent"}
    z = load_npz(src / "meshes.npz")
    Vt, Ft, Lt = z["vertices"].astype(np.float64), z["faces"].astype(np.int64), z["labels"].astype(np.int64)
    # the map from the true template (first frame) to the prepared one: copied body vertices,
    # and for every other vertex a true triangle of its own part and barycentric coordinates
    body_new, body_true = np.flatnonzero(labels == 0), np.flatnonzero(Lt == 0)
    done = np.zeros(len(vertices), bool)
    copy = len(body_new) == len(body_true) and np.abs(vertices[body_new] - Vt[0, body_true]).max() < 1e-3
    if copy:
        done[body_new] = True
    maps = []
    for part in (0, 1):  # body, garments: each from the true surface of the same part
        sel = np.flatnonzero(~done & ((labels > 0) == bool(part)))
        tf = Ft[((Lt[Ft] > 0) == bool(part)).all(1)]
        if not len(sel) or not len(tf):
            continue
        _, f, w, _ = MeshQuery(Vt[0], tf, spacing=0.02).closest(vertices[sel])
        maps.append((sel, tf[f], w))
        done[sel] = True

    def express(V: np.ndarray) -> np.ndarray:
        out = np.empty((len(V), len(vertices), 3))
        if copy:
            out[:, body_new] = V[:, body_true]
        for sel, tri, w in maps:
            out[:, sel] = np.einsum("nk,tnkd->tnd", w, V[:, tri])
        return out

    info = {"meshes": "re-expressed on the prepared template", "body_copied": bool(copy)}
    for m in meshes:
        if not (src / m).is_file():
            continue
        zm = z if m == "meshes.npz" else load_npz(src / m)
        Vm = zm["vertices"].astype(np.float64)
        if Vm.shape[1] != len(Vt[0]):  # another topology than the template's: left as it is
            link_file(src / m, dst / m)
            info[m] = "linked (not on the template's vertices)"
            continue
        save_npz_atomic(dst / m, vertices=express(Vm).astype(np.float32), faces=faces,
                        labels=labels.astype(np.uint8), fps=zm.get("fps", np.array(25.0)),
                        note=np.array("re-expressed on the prepared template (closest true surface points)"))
        info[m] = "re-expressed"
    return info
