"""What the fit leaves in its folder, read and written here: the per-iteration log
(``fit_log.csv``), the loss plot (``loss.png``) and the fitted appearance as a whole
(:class:`FittedAppearance`: texture, atlas, lights)."""

from __future__ import annotations

import csv
import io
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ...errors import PhysavatarError
from ...files import atomic_path, load_npz, write_text_atomic
from ...render.lights import load_lights

LOG_COLUMNS = ("iteration", "loss", "lr", "ambient_r", "ambient_g", "ambient_b", "key", "seconds")


def write_log(path: Path, rows: list[dict]) -> None:
    """``fit_log.csv`` (columns :data:`LOG_COLUMNS`, floats to 6 significant digits), atomically."""
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=LOG_COLUMNS)
    w.writeheader()
    for r in rows:
        w.writerow({k: (f"{v:.6g}" if isinstance(v, float) else v) for k, v in r.items()})
    write_text_atomic(path, buf.getvalue())


def read_log(path: Path) -> list[dict]:
    """The rows of ``fit_log.csv`` ([] when there is none)."""
    if not path.is_file():
        return []
    with open(path) as f:
        return [{k: (int(v) if k == "iteration" else float(v)) for k, v in r.items()} for r in csv.DictReader(f)]


def plot_loss(log: list[dict], path: Path) -> None:
    """Loss per iteration (and its running mean: single random views are noisy) as a PNG."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    if not log:
        return
    it = np.array([r["iteration"] for r in log])
    loss = np.array([r["loss"] for r in log])
    k = max(1, min(100, len(loss) // 10))  # views differ ~10x in loss: average many
    smooth = np.convolve(loss, np.ones(k) / k, mode="valid")
    fig, ax = plt.subplots(figsize=(6, 3.5), dpi=100)
    ax.semilogy(it, loss, lw=0.5, alpha=0.4, label="loss (one random view)")
    ax.semilogy(it[k - 1:], smooth, lw=1.5, label=f"running mean ({k})")
    ax.set_xlabel("iteration")
    ax.set_ylabel("masked MSE (linear RGB)")
    ax.legend()
    ax.grid(alpha=0.3)
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png")
    plt.close(fig)


@dataclass
class FittedAppearance:
    """A fit's output folder loaded: texture [H, W, 3] linear, face_uvs [F, 3, 2], lights."""

    texture: np.ndarray
    texture_init: np.ndarray | None
    face_uvs: np.ndarray
    lights: list

    @staticmethod
    def load(folder: str | Path) -> FittedAppearance:
        folder = Path(folder)
        p = folder / "texture_linear.npy"
        if not p.is_file():
            raise PhysavatarError(p, "file not found (is this a fit-appearance output folder?)")
        init = folder / "texture_init_linear.npy"
        return FittedAppearance(np.load(p), np.load(init) if init.is_file() else None,
                                load_npz(folder / "atlas.npz")["face_uvs"], load_lights(folder / "light.json"))
