"""Quick looks at a motion: the posed (decimated) body and skeleton, front and side, as GIF/MP4.

A matplotlib painter's-algorithm render (faces sorted by depth, Lambert shading), so it needs no
renderer and runs in seconds; the real renders come from ``physavatar.render``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..files import atomic_path


def _shade(verts2d, depth, faces, normals, ax, color):
    from matplotlib.collections import PolyCollection

    order = np.argsort(-depth)  # far to near
    light = np.array([0.3, -0.6, 0.75])
    light /= np.linalg.norm(light)
    lam = np.clip(np.abs(normals @ light), 0, 1)[order]
    cols = np.clip(np.asarray(color)[None] * (0.35 + 0.65 * lam[:, None]), 0, 1)
    pc = PolyCollection(verts2d[faces[order]], facecolors=cols, edgecolors="none", antialiased=False)
    ax.add_collection(pc)


def render_frames(vertices: np.ndarray, faces: np.ndarray, joints: np.ndarray | None, parents: np.ndarray | None,
                  size: int = 320, title: str = "", progress=None) -> list[np.ndarray]:
    """Images [H, W, 3] uint8 of each frame: front view (from -y) and side view (from +x).

    Args:
        vertices: [T, V, 3]; faces: [F, 3]; joints: [T, B, 3] or None; parents: [B].
        progress: see :mod:`physavatar.progress`.
    """
    from ..progress import resolve

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    T = vertices.shape[0]
    lo = vertices.reshape(-1, 3).min(0)
    hi = vertices.reshape(-1, 3).max(0)
    c = 0.5 * (lo + hi)
    r = 0.55 * float((hi - lo).max())
    views = [("front", 0, 2, 1, -1.0), ("side", 1, 2, 0, 1.0)]  # (name, u axis, v axis, depth axis, sign)
    frames = []
    fig, axes = plt.subplots(1, 2, figsize=(2 * size / 100, size / 100), dpi=100)
    task = resolve(progress).task("preview", total=T)
    for t in range(T):
        v = vertices[t]
        tri = v[faces]
        n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        n /= np.linalg.norm(n, axis=1, keepdims=True) + 1e-12
        for ax, (name, ua, va, da, sgn) in zip(axes, views):
            ax.clear()
            ax.set_xlim(c[ua] - r, c[ua] + r)
            ax.set_ylim(c[va] - r, c[va] + r)
            ax.set_aspect("equal")
            ax.axis("off")
            uv = v[:, [ua, va]]  # front: image right = +x; side (from +x): image right = +y
            depth = sgn * tri[:, :, da].mean(1) * (-1)
            _shade(uv, depth, faces, n, ax, (0.80, 0.66, 0.55))
            if joints is not None and parents is not None:
                J = joints[t]
                ju = J[:, [ua, va]]
                for b, p in enumerate(parents):
                    if p >= 0:
                        ax.plot(ju[[p, b], 0], ju[[p, b], 1], color=(0.1, 0.3, 0.8), lw=0.8, alpha=0.7)
            ax.axhline(0.0, color=(0.5, 0.5, 0.5), lw=0.5)
            ax.set_title(f"{title} {name}  frame {t}", fontsize=7)
        fig.tight_layout(pad=0.2)
        fig.canvas.draw()
        img = np.asarray(fig.canvas.buffer_rgba())[..., :3].copy()
        frames.append(img)
        task.advance()
    task.end()
    plt.close(fig)
    return frames


def write_video(path: str | Path, frames: list[np.ndarray], fps: float) -> None:
    """Write frames as .gif or .mp4 (imageio / imageio-ffmpeg), atomically."""
    import imageio.v2 as imageio

    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in (".gif", ".mp4"):
        raise ValueError(f"{path}: preview must be .gif or .mp4")
    with atomic_path(path) as tmp:
        if suffix == ".gif":
            imageio.mimsave(tmp, frames, format="GIF", duration=1.0 / fps, loop=0)
        else:
            h, w = frames[0].shape[:2]
            # H.264 needs even sizes
            fr = [f[: h - h % 2, : w - w % 2] for f in frames]
            imageio.mimsave(tmp, fr, format="FFMPEG", fps=fps, codec="libx264", quality=7,
                            macro_block_size=1, ffmpeg_log_level="error")
