"""UV atlas of the prepared template by xatlas (charts, packing): per-corner UVs [F, 3, 2]."""

from __future__ import annotations

import numpy as np


def atlas(vertices: np.ndarray, faces: np.ndarray, resolution: int = 1024, padding: int = 2) -> np.ndarray:
    """[F, 3, 2] per-corner UVs in [0, 1] of the mesh (xatlas keeps the faces' order)."""
    import xatlas

    atl = xatlas.Atlas()
    atl.add_mesh(np.ascontiguousarray(vertices, np.float32), np.ascontiguousarray(faces, np.uint32))
    pack = xatlas.PackOptions()
    pack.resolution = resolution
    pack.padding = padding
    atl.generate(xatlas.ChartOptions(), pack)
    _, idx, uvs = atl[0]
    out = np.asarray(uvs, np.float64)[np.asarray(idx, np.int64)]
    if out.shape != (len(faces), 3, 2):
        raise RuntimeError(f"xatlas returned {out.shape[0]} faces for {len(faces)}")
    return out
