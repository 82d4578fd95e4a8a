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
