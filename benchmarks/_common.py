"""Helpers shared by the benchmark scripts (run as `python benchmarks/NAME.py`)."""

import platform

import numpy as np


def cpu_name() -> str:
    """The CPU model, for the `machine` field of benchmarks/results/*.json."""
    try:
        for line in open("/proc/cpuinfo"):
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown"


def quarter_ratio(per_frame: list[float]) -> float:
    """Mean of the last quarter over the first quarter of the frames after the first."""
    e = np.asarray(per_frame[1:], float)
    if len(e) < 4:
        return float("nan")
    q = max(1, len(e) // 4)
    return float(e[-q:].mean() / max(e[:q].mean(), 1e-9))


def machine(load0) -> dict:
    """The ``machine`` field of a result file: cores, CPU, the load average at the start (``load0``) and now."""
    import os

    return {"cores": os.cpu_count(), "cpu": cpu_name(), "load_average_start": list(load0),
            "load_average_end": list(os.getloadavg())}


def write_result(path, result: dict) -> None:
    """Writes a benchmark's result dict to ``path`` (JSON; its folder made)."""
    import json
    from pathlib import Path

    Path(path).parent.mkdir(parents=True, exist_ok=True)
    Path(path).write_text(json.dumps(result, indent=2) + "\n")


def animate_scored(av, held, gt, points: int = 10000, **animate_kw):
    """The avatar ``av`` animated on the held-out motion ``held`` as `evaluate` animates it, its
    garment scored as `evaluate` scores it against ``gt`` [T, V, 3] (the true held-out meshes on the
    template's vertices): seed 0 at ``points`` surface points. Returns (``_surface_rows``' row,
    animate's stats, its seconds, the simulated garment [T, Ng, 3])."""
    import time

    from physavatar.geometry import submesh
    from physavatar.stages.animate import animate
    from physavatar.stages.evaluate import _surface_rows

    t0 = time.time()
    seq, stats = animate(av, held, progress=False, **animate_kw)
    secs = time.time() - t0
    g = av.template.labels > 0
    _, gf = submesh(av.template.faces, g)
    V = seq.vertices[: len(gt)][:, g]
    return _surface_rows(V, gt[:, g], gf, points, 0), stats, secs, V


def write_heldout_result(path, benchmark: str, load0, fields: dict, results: dict, unit: str) -> None:
    """Writes a held-out Chamfer benchmark's result file ``path`` (`prepare_heldout_parts`,
    `prepare_garment_parts`): the machine with the load at the start and now, ``fields``, the
    ``variants`` and one reported check per variant (its ``chamfer_x1e3``)."""
    import datetime

    result = {"benchmark": benchmark, "date": datetime.datetime.now().isoformat(timespec="seconds"),
            "machine": machine(load0), **fields, "variants": results,
            "checks": {f"heldout_garment_cd_x1e3/{k}": {"value": r.get("chamfer_x1e3"), "target": "reported",
                                                         "unit": unit, "pass": True}
                       for k, r in results.items()}}
    write_result(path, result)
