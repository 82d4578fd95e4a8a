"""``OUT/report.md`` of a ``physavatar run``: metrics, textures before/after, novel views, loss
plots, the outputs and every stage's wall time and equivalent command."""

from __future__ import annotations

import os
from pathlib import Path

from .files import read_json


def write_report(out: str | Path) -> Path:
    """OUT/report.md: metrics, textures before/after, novel views, loss plots, stage wall times."""
    from .files import write_text_atomic

    out = Path(out)
    rec = read_json(out / "run.json") if (out / "run.json").exists() else {}
    L = ["# physavatar run", ""]
    cap = rec.get("_capture")
    if cap:
        L += [f"Capture `{cap}`, output `{out}`. Every stage's command is in the last table; "
              "`physavatar run` with the same arguments resumes or skips finished stages (a stage runs again when "
              "its config or inputs change).", ""]
    ev = out / "evaluate" / "report.md"
    if ev.exists():
        body = ev.read_text().split("\n", 1)[1]  # drop its title
        L += ["## Metrics", body.replace("\n## ", "\n### "), ""]
    _tracking_plot(out)
    _texture_pngs(out)
    pics = [("Tracking: loss and time per frame (and vertex error against ground truth)", "tracking.png"),
            ("Texture before inverse rendering (mean tracked Gaussian colours)", "texture_before.png"),
            ("Texture after inverse rendering", "appearance/texture.png"),
            ("Appearance fit: loss", "appearance/loss.png"),
            ("Material fit: loss and parameters", "physics/fit.png")]
    shown = [(t, p) for t, p in pics if (out / p).exists()]
    if shown:
        L += ["## Pictures", ""]
        for title, p in shown:
            L += [f"**{title}**", "", f"![{title}]({p})", ""]
    for folder, title in (("render", "Novel views of the held-out motion under the fitted light"),
                          ("relight", "Relit under a sky environment map")):
        frames = sorted((out / folder / "frames" / "orbit").glob("*.png"))
        if frames:
            pick = [frames[0], frames[len(frames) // 2], frames[-1]]
            L += [f"**{title}** ({folder}/orbit.mp4)", ""] + [f"![frame]({p.relative_to(out)})" for p in pick] + [""]
    for folder, title in (("views", "Held-out motion, held-out view: ours | ground truth"),
                          ("holdout_views", "Held-out camera of the capture: ours | the capture's image")):
        views = sorted((out / "evaluate" / folder).glob("*_ours.png"))
        if views:
            v = views[len(views) // 2]
            L += [f"**{title}**", "", f"![ours]({v.relative_to(out)}) "
                  f"![gt]({(v.parent / v.name.replace('_ours', '_gt')).relative_to(out)})", ""]
    outputs = [("avatar/", "the avatar: template, skinning weights, material, texture, light"),
               ("animate/", "the held-out animation: sequence.npz and one PLY per frame"),
               ("render/orbit.mp4", "novel views under the fitted light"),
               ("relight/orbit.mp4", "relit under a sky environment map"),
               ("export/avatar.usdc", "USD with time-sampled points, UVs and the texture (Blender: File > Import > USD)"),
               ("export-glb/avatar.glb", "glTF binary with morph-target animation"),
               ("physics/material.json", "the fitted cloth material with its intervals")]
    outputs = [(p, d) for p, d in outputs if (out / p).exists()]
    if outputs:
        L += ["## Outputs", "", "| path | what |", "| --- | --- |"] + [f"| `{p}` | {d} |" for p, d in outputs] + [""]
    L += _view_html(out)
    times = [(k, v) for k, v in rec.items() if isinstance(v, dict) and "seconds" in v]
    if times:
        import platform

        cores = os.cpu_count()
        L += [f"## Wall time per stage ({cores}-core CPU, {platform.machine()})", "",
              "| stage | seconds | status | command |", "| --- | --- | --- | --- |"]
        L += [f"| {k} | {v['seconds']}{' (beside)' if v.get('background') else ''} | {v.get('status', '')} | "
              f"`physavatar {' '.join(v.get('command', []))}` |" for k, v in times]
        L += [f"| **total** | {sum(v['seconds'] for _, v in times if not v.get('background')):.1f} | | |", ""]
        if any(v.get("background") for _, v in times):
            L += ["Stages marked *beside* ran on the second core while the stages after them ran; "
                  "the total leaves them out (it is the wall time of the stages in line).", ""]
    path = out / "report.md"
    write_text_atomic(path, "\n".join(L) + "\n")
    return path


def _view_html(out: Path) -> list[str]:
    """OUT/view.html: the run folder's viewer scene (``physavatar view OUT --save``, the first
    :data:`~physavatar.viewer.server.REPORT_FRAMES` frames) and the report's lines linking it. It
    never fails the report: a failure is a line saying why."""
    if not (out / "run.json").exists():
        return []
    L = ["## Viewer", ""]
    try:
        import time

        from .viewer.server import REPORT_FRAMES, save_view

        t0 = time.perf_counter()
        path = save_view(out, out / "view.html", max_frames=REPORT_FRAMES)
        L += [f"[view.html](view.html) plays the run's meshes (the first {REPORT_FRAMES} frames at most) with the "
              f"capture's cameras in a browser, no server needed ({path.stat().st_size / 1e6:.1f} MB, written in "
              f"{time.perf_counter() - t0:.1f} s). `physavatar view {out}` serves every layer with the time "
              "slider, toggles, error colouring and panels (docs/viewer.md).", ""]
    except Exception as e:  # noqa: BLE001 -- a viewer file is a convenience, never a failed run
        (out / "view.html").unlink(missing_ok=True)
        L += [f"view.html was not written ({type(e).__name__}: {e}); `physavatar view {out}` may still serve "
              "the run (docs/viewer.md).", ""]
    return L


def _tracking_plot(out: Path) -> None:
    """OUT/tracking.png from track/track_log.csv, retrack's with two passes (+ the evaluation's
    per-frame vertex error, of the same pass)."""
    import csv

    log = next((p for p in (out / "retrack" / "track_log.csv", out / "track" / "track_log.csv") if p.exists()),
               out / "track" / "track_log.csv")
    if not log.exists():
        return
    try:
        rows = list(csv.DictReader(log.open()))
        frames = [int(r["frame"]) for r in rows]
        loss = [float(r["loss"]) for r in rows]
        secs = [float(r["seconds"]) for r in rows]
    except (KeyError, ValueError, OSError):
        return  # a log of another format: no plot rather than a broken report
    err = {}
    metrics = out / "evaluate" / "metrics.json"
    if metrics.exists():
        err = {p: r.get("per_frame_mean_mm", []) for p, r in read_json(metrics).get("tracking", {}).items()}
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from .files import atomic_path

    n = 3 if err else 2
    fig, ax = plt.subplots(1, n, figsize=(4 * n, 3.2))
    ax[0].semilogy(frames, loss)
    ax[0].set(xlabel="frame", title="L_render + regularizers")
    ax[1].bar(frames, secs)
    ax[1].set(xlabel="frame", ylabel="s", title="tracking time")
    if err:
        for part, e in err.items():
            ax[2].plot(range(len(e)), e, label=part)
        ax[2].set(xlabel="frame", ylabel="mm", title="mean vertex error")
        ax[2].legend()
    fig.tight_layout()
    with atomic_path(out / "tracking.png") as tmp:
        fig.savefig(tmp, dpi=100)
    plt.close(fig)


def _texture_pngs(out: Path) -> None:
    """OUT/texture_before.png (the appearance stage's T_0, sRGB) for the before/after pictures."""
    import numpy as np

    src = out / "appearance" / "texture_init_linear.npy"
    dst = out / "texture_before.png"
    if not src.exists() or (dst.exists() and dst.stat().st_mtime >= src.stat().st_mtime):
        return
    from .capture import save_png
    from .render import linear_to_srgb8

    save_png(dst, linear_to_srgb8(np.load(src)))
