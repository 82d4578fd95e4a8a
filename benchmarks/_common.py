"""Helpers shared by the benchmark scripts (run as `python benchmarks/NAME.py`)."""

import platform


def cpu_name() -> str:
    """The CPU model, for the `machine` field of benchmarks/results/*.json."""
    try:
        for line in open("/proc/cpuinfo"):
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown"
