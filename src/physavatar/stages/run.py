"""``physavatar run CAPTURE OUT``: the whole pipeline, resumable.

track -> fit-physics -> fit-appearance -> build-avatar -> animate (held-out motion) -> render ->
evaluate -> report. Each stage runs as its own ``physavatar`` command (the same one a user would
type) writing into ``OUT/<stage>/``; a stage whose final output exists and whose command line is
unchanged (recorded in ``OUT/run.json``) is skipped, so an interrupted run resumes where it
stopped, and the stages' own resume logic (tracking per frame) picks up inside a stage.

Stages that need nothing from the ones in between run *beside* them on a spare core (output to
``OUT/<stage>/stage.log``): the evaluation's reference simulations (``reference-sims``) beside
tracking, which is single-threaded, and fit-appearance (Mitsuba) beside fit-physics. A stage
that needs one of them waits for it. On a one-core machine everything runs in line.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

from ..errors import PhysavatarError
from ..files import read_json, write_json_atomic
from ..parallel import default_workers


@dataclass
class Stage:
    name: str
    args: list[str]
    done_file: str  # relative to OUT/<name>
    needs: tuple[str, ...] = ()  # background stages this one must wait for
    # Runs beside the following stages on a spare core (its output goes to OUT/<name>/stage.log)
    # when one is free (at most cores - 1 stages run beside); in line otherwise.
    background: bool = False

    def done(self, out: Path, record: dict) -> bool:
        return (out / self.name / self.done_file).exists() and record.get(self.name, {}).get("args") == self.args


# The CPU schedule of the stages whose paper budgets are GPU budgets (docs/evaluation.md gives
# the measured times on the demo capture). Tracking and material fitting use their commands'
# defaults, which are already CPU schedules (docs/tracking.md, docs/physics.md).
APPEARANCE_CPU = ["--iterations", "300", "--scale", "0.5", "--lr", "0.02", "--decay-every", "100",
                  "--final-spp", "64"]
APPEARANCE_QUICK = ["--quick"]
# Material fitting: the first 12 frames (the paper fits 24) and at most 8 LM iterations. On the
# demo this halves the stage (190 s at load 2 on a 1,200-vertex proxy) and fits the frames the
# tracking gets best (its error grows over the walk: docs/tracking.md).
PHYSICS_CPU = ["--window", "12", "--iterations", "8"]
RENDER_SPP, RENDER_SPP_QUICK = "32", "16"


def plan(capture: Path, out: Path, *, quick: bool = False, heldout_motion: str | None = None,
         track_frames: int | None = None, eval_frames: int | None = None) -> list[Stage]:
    cap, o = str(capture), str(out)
    track = ["track", cap, "--out", f"{o}/track"] + (["--frames", str(track_frames)] if track_frames else [])
    physics = ["fit-physics", f"{o}/track", "--out", f"{o}/physics"] + \
        (["--iterations", "3", "--window", "6"] if quick else PHYSICS_CPU)
    appearance = ["fit-appearance", cap, "--tracked", f"{o}/track", "--out", f"{o}/appearance"] + \
        (APPEARANCE_QUICK if quick else APPEARANCE_CPU)
    avatar = ["build-avatar", cap, "--out", f"{o}/avatar", "--material", f"{o}/physics/material.json",
              "--appearance", f"{o}/appearance"]
    held_file = Path(cap) / "ground_truth" / "heldout" / "motion.npz"
    motion = heldout_motion or (str(held_file) if held_file.exists() else "dance")
    animate = ["animate", f"{o}/avatar", "--motion", motion, "--out", f"{o}/animate"] + \
        (["--max-frames", str(eval_frames)] if eval_frames else [])
    size = ["--size", "128"] if quick else []
    spp = RENDER_SPP_QUICK if quick else RENDER_SPP
    render = ["render", f"{o}/animate", "--out", f"{o}/render", "--light", "fitted", "--spp", spp] + size
    relight = ["render", f"{o}/animate", "--out", f"{o}/relight", "--light", "sky", "--spp", spp] + size
    export = ["export", f"{o}/animate", "--out", f"{o}/export/avatar.usdc"]
    export_glb = ["export", f"{o}/animate", "--out", f"{o}/export-glb/avatar.glb"]
    # fit-appearance (Mitsuba, multi-threaded) runs beside fit-physics (single-threaded
    # simulations): both need only the tracking.
    stages = [Stage("track", track, "tracked.npz"),
              Stage("appearance", appearance, "texture.png", background=True),
              Stage("physics", physics, "material.json"),
              Stage("avatar", avatar, "avatar.json", needs=("appearance",)),
              Stage("animate", animate, "sequence.json"), Stage("render", render, "render.json"),
              Stage("relight", relight, "render.json"), Stage("export", export, "avatar.usdc"),
              Stage("export-glb", export_glb, "avatar.glb")]
    # Evaluation needs ground truth: synthetic captures only.
    if held_file.exists() and (Path(cap) / "ground_truth" / "heldout" / "meshes.npz").exists():
        # The true- and random-material rows need nothing fitted: simulated on the second core
        # while tracking (single-threaded) runs on the first.
        frames = ["--frames", str(eval_frames)] if eval_frames else []
        refs = Stage("references", ["reference-sims", cap, "--out", f"{o}/references"] + frames, "references.json",
                     background=True)
        stages.insert(0, refs)  # first: it starts, then tracking runs in line beside it
        evaluate = ["evaluate", cap, "--avatar", f"{o}/avatar", "--tracked", f"{o}/track", "--out", f"{o}/evaluate",
                    "--references", f"{o}/references"]
        if heldout_motion is None:  # the animate stage ran the held-out motion: reuse it
            evaluate += ["--sequence", f"{o}/animate"]
        evaluate += frames
        stages.append(Stage("evaluate", evaluate, "metrics.json", needs=("references",)))
    return stages


def run_pipeline(capture: str | Path, out: str | Path, *, only: list[str] | None = None, **plan_kw) -> dict:
    """Run (or resume) every stage; returns the run record (per-stage seconds and status)."""
    from rich.console import Console

    console = Console()
    capture, out = Path(capture), Path(out)
    if not capture.is_dir():
        raise PhysavatarError(capture, "capture folder not found")
    out.mkdir(parents=True, exist_ok=True)
    rec_path = out / "run.json"
    record = read_json(rec_path) if rec_path.exists() else {}
    stages = plan(capture, out, **plan_kw)
    env = dict(os.environ)
    cores = default_workers(64)
    t_all = time.time()
    background: dict[str, tuple[subprocess.Popen, float, Stage]] = {}
    ended = _EndTimes()  # when each background stage really ended (it is reaped later)

    def finish(name: str) -> None:
        """Wait for background stage ``name`` and record it; raise if it failed."""
        proc, t0, st = background.pop(name)
        if proc.poll() is None:
            console.print(f"[dim]waiting for {name} (running beside since {time.time() - t0:.0f} s; "
                          f"log: {out / name / 'stage.log'})[/]")
        rc = proc.wait()
        ended.wait(name)
        _record(st, rc, round(ended.at.get(name, time.time()) - t0, 1), background=True)
        console.print(f"[dim]{name} (beside the other stages): {'done' if rc == 0 else 'failed'} "
                      f"after {record[name]['seconds']} s[/]")

    def _record(st: Stage, rc: int, secs: float, background: bool = False) -> None:
        if rc == 130:
            raise KeyboardInterrupt
        status = "ok" if rc == 0 else f"failed ({rc})"
        record[st.name] = {"args": st.args, "seconds": secs, "status": status} | ({"background": True} if background else {})
        write_json_atomic(rec_path, record)
        if rc != 0:
            where = out / st.name / "stage.log" if background else out / st.name
            raise PhysavatarError(where, f"stage {st.name!r} failed (exit code {rc}); "
                                  f"fix the cause and run again to resume")

    try:
        for i, st in enumerate(stages, 1):
            if only and st.name not in only:
                continue
            if st.done(out, record):
                console.print(f"[dim][{i}/{len(stages)}] {st.name}: done earlier ({record[st.name].get('seconds', '?')} s), skipped[/]")
                continue
            for name in [n for n, (p, _, _) in background.items() if p.poll() is not None]:
                finish(name)  # ended meanwhile: its core is free again
            if st.background and len(background) < cores - 1:
                (out / st.name).mkdir(parents=True, exist_ok=True)
                log = open(out / st.name / "stage.log", "w")
                benv = env | {"PHYSAVATAR_WORKERS": "1"}  # one core: the other runs the next stages
                proc = subprocess.Popen([sys.executable, "-m", "physavatar.cli", *st.args], env=benv,
                                        stdout=log, stderr=subprocess.STDOUT)
                log.close()
                background[st.name] = (proc, time.time(), st)
                ended.watch(st.name, proc)
                console.print(f"[bold][{i}/{len(stages)}] {st.name}[/]: physavatar {' '.join(st.args)}  "
                              f"[dim](beside the next stages on the second core; log: {out / st.name / 'stage.log'})[/]")
                continue
            for name in st.needs:
                if name in background:
                    finish(name)
            console.rule(f"[bold][{i}/{len(stages)}] {st.name}[/]: physavatar {' '.join(st.args)}")
            t0 = time.time()
            proc = subprocess.run([sys.executable, "-m", "physavatar.cli", *st.args], env=env)
            _record(st, proc.returncode, round(time.time() - t0, 1))
        for name in list(background):
            finish(name)
    finally:
        for proc, _, _ in background.values():  # interrupted or failed: stop what runs beside
            proc.terminate()
            proc.wait()
    record["_total_seconds_this_run"] = round(time.time() - t_all, 1)
    write_json_atomic(rec_path, record)
    return record


class _EndTimes:
    """The wall-clock end of background processes, noted by one watcher thread each."""

    def __init__(self):
        import threading

        self.at: dict[str, float] = {}
        self._threads: dict = {}
        self._threading = threading

    def watch(self, name: str, proc: subprocess.Popen) -> None:
        def note():
            proc.wait()
            self.at[name] = time.time()

        t = self._threading.Thread(target=note, daemon=True)
        t.start()
        self._threads[name] = t

    def wait(self, name: str) -> None:
        t = self._threads.get(name)
        if t is not None:
            t.join(timeout=5.0)


def write_report(out: str | Path) -> Path:
    """OUT/report.md: metrics, textures before/after, novel views, loss plots, stage wall times."""
    from ..files import write_text_atomic

    out = Path(out)
    rec = read_json(out / "run.json") if (out / "run.json").exists() else {}
    L = ["# physavatar run", ""]
    cap = rec.get("track", {}).get("args", [None, None])[1]
    if cap:
        L += [f"Capture `{cap}`, output `{out}`. Every stage's command is in the last table; "
              "`physavatar run` with the same arguments resumes or skips finished stages.", ""]
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
    views = sorted((out / "evaluate" / "views").glob("*_ours.png"))
    if views:
        v = views[len(views) // 2]
        L += ["**Held-out view: ours | ground truth**", "", f"![ours]({v.relative_to(out)}) "
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
    times = [(k, v) for k, v in rec.items() if isinstance(v, dict) and "seconds" in v]
    if times:
        import platform

        cores = os.cpu_count()
        L += [f"## Wall time per stage ({cores}-core CPU, {platform.machine()})", "",
              "| stage | seconds | status | command |", "| --- | --- | --- | --- |"]
        L += [f"| {k} | {v['seconds']}{' (beside)' if v.get('background') else ''} | {v.get('status', '')} | "
              f"`physavatar {' '.join(v.get('args', []))}` |" for k, v in times]
        L += [f"| **total** | {sum(v['seconds'] for _, v in times if not v.get('background')):.1f} | | |", ""]
        if any(v.get("background") for _, v in times):
            L += ["Stages marked *beside* ran on the second core while the stages after them ran; "
                  "the total leaves them out (it is the wall time of the stages in line).", ""]
    path = out / "report.md"
    write_text_atomic(path, "\n".join(L) + "\n")
    return path


def _tracking_plot(out: Path) -> None:
    """OUT/tracking.png from track/track_log.csv (+ the evaluation's per-frame vertex error)."""
    import csv

    log = out / "track" / "track_log.csv"
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

    from ..files import atomic_path

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
    from ..capture import save_png
    from ..render import linear_to_srgb8

    save_png(dst, linear_to_srgb8(np.load(src)))
