"""Memory and frame-switch latency of ``physavatar view`` on a large sequence (issue 26):
an animate folder of T frames x ~N vertices is synthesized, opened by the viewer (memory-mapped),
and every frame is shown once. Usage: viewer_latency.py [OUT] [T] [N]. Not a test."""

import resource
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from physavatar.data.animated import AnimatedSequence
from physavatar.viewer import Viewer, load_scene


def rss_mb(kind: str = "RssAnon") -> float:
    """Resident memory of this process: ``RssAnon`` (its own arrays) or ``RssFile`` (mapped files,
    page cache the kernel can drop)."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith(kind + ":"):
            return int(line.split()[1]) / 1024
    return float("nan")


def main(out: Path, T: int = 200, N: int = 30000) -> None:
    if not (out / "sequence.npz").is_file():
        make(out, T, N)
    r0, f0 = rss_mb(), rss_mb("RssFile")
    t0 = time.perf_counter()
    scene = load_scene(out)
    t_load = time.perf_counter() - t0
    r1, f1 = rss_mb(), rss_mb("RssFile")
    with Viewer(scene) as view:
        r2 = rss_mb()
        times = []
        for f in range(scene.n_frames):
            t0 = time.perf_counter()
            view.set_frame(f)
            times.append(time.perf_counter() - t0)
        r3, f3 = rss_mb(), rss_mb("RssFile")
    ms = np.array(times) * 1000
    print(f"{scene.n_frames} frames x {scene.layers[0].vertices.shape[1]} vertices; opened in {t_load:.2f} s "
          f"(memory-mapped, with the NaN scan); anonymous RSS {r0:.0f} MB before, +{r1 - r0:.0f} MB opened, "
          f"+{r2 - r0:.0f} MB with the server up, +{r3 - r0:.0f} MB after showing every frame; "
          f"file-backed (droppable page cache) +{f1 - f0:.0f} MB opened, +{f3 - f0:.0f} MB at the end; "
          f"peak RSS {resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024:.0f} MB")
    print(f"frame switch (server side: read the frame, send it): median {np.median(ms):.1f} ms, "
          f"p95 {np.percentile(ms, 95):.1f} ms, max {ms.max():.1f} ms")


def make(out: Path, T: int, N: int) -> None:
    n = int(np.sqrt(N))
    u, v = np.meshgrid(np.linspace(0, 2 * np.pi, n), np.linspace(0.1, np.pi - 0.1, n))
    base = np.stack([np.sin(v) * np.cos(u), np.sin(v) * np.sin(u), np.cos(v) + 1.2], -1).reshape(-1, 3) * 0.5
    i = np.arange(n - 1)[:, None] * n + np.arange(n - 1)[None, :]
    faces = np.concatenate([np.stack([i, i + 1, i + n], -1).reshape(-1, 3), np.stack([i + 1, i + n + 1, i + n], -1).reshape(-1, 3)])
    labels = (np.arange(len(base)) >= len(base) // 2).astype(np.uint8)
    t = np.linspace(0, 2 * np.pi, T)[:, None, None]
    V = (base[None] * (1 + 0.1 * np.sin(t + base[None, :, 2:3] * 6))).astype(np.float32)
    V[T // 2] = np.nan  # one NaN frame
    AnimatedSequence(V, faces, labels, None, 30.0).save(out, {"command": "viewer_latency"}, ply=False)
    print(f"wrote {out}: {T} frames x {len(base)} vertices, {len(faces)} faces ({V.nbytes / 1e6:.0f} MB float32)")


if __name__ == "__main__":
    args = sys.argv[1:]
    out = Path(args[0]) if args else Path(tempfile.mkdtemp()) / "animate"
    main(out, *(int(a) for a in args[1:3]))
