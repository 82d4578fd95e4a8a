"""``physavatar run CAPTURE OUT``: the whole pipeline, resumable.

track -> fit-physics -> fit-appearance -> build-avatar -> animate (held-out motion) -> render ->
evaluate -> report. Each stage runs as its own ``physavatar`` command (the same one a user would
type) writing into ``OUT/<stage>/``; a stage whose final output exists and whose command line is
unchanged (recorded in ``OUT/run.json``) is skipped, so an interrupted run resumes where it
stopped, and the stages' own resume logic (tracking per frame) picks up inside a stage.
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


@dataclass
class Stage:
    name: str
    args: list[str]
    done_file: str  # relative to OUT/<name>

    def done(self, out: Path, record: dict) -> bool:
        return (out / self.name / self.done_file).exists() and record.get(self.name, {}).get("args") == self.args


def plan(capture: Path, out: Path, *, quick: bool = False, heldout_motion: str | None = None,
         track_frames: int | None = None, eval_frames: int | None = None) -> list[Stage]:
    cap, o = str(capture), str(out)
    track = ["track", cap, "--out", f"{o}/track"] + (["--frames", str(track_frames)] if track_frames else [])
    physics = ["fit-physics", f"{o}/track", "--out", f"{o}/physics"] + \
        (["--iterations", "3", "--window", "6"] if quick else [])
    appearance = ["fit-appearance", cap, "--tracked", f"{o}/track", "--out", f"{o}/appearance"] + (["--quick"] if quick else [])
    avatar = ["build-avatar", cap, "--out", f"{o}/avatar", "--material", f"{o}/physics/material.json",
              "--appearance", f"{o}/appearance"]
    motion = heldout_motion or f"{cap}/ground_truth/heldout/motion.npz"
    animate = ["animate", f"{o}/avatar", "--motion", motion, "--out", f"{o}/animate"] + \
        (["--max-frames", str(eval_frames)] if eval_frames else [])
    size = ["--size", "128"] if quick else []
    render = ["render", f"{o}/animate", "--out", f"{o}/render", "--light", "fitted", "--spp", "16" if quick else "64"] + size
    relight = ["render", f"{o}/animate", "--out", f"{o}/relight", "--light", "sky", "--spp", "16" if quick else "64"] + size
    evaluate = ["evaluate", cap, "--avatar", f"{o}/avatar", "--tracked", f"{o}/track", "--out", f"{o}/evaluate"] + \
        (["--frames", str(eval_frames)] if eval_frames else [])
    return [Stage("track", track, "tracked.npz"), Stage("physics", physics, "material.json"),
            Stage("appearance", appearance, "texture.png"), Stage("avatar", avatar, "avatar.json"),
            Stage("animate", animate, "sequence.json"), Stage("render", render, "render.json"),
            Stage("relight", relight, "render.json"), Stage("evaluate", evaluate, "metrics.json")]


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
    t_all = time.time()
    for i, st in enumerate(stages, 1):
        if only and st.name not in only:
            continue
        if st.done(out, record):
            console.print(f"[dim][{i}/{len(stages)}] {st.name}: done earlier ({record[st.name].get('seconds', '?')} s), skipped[/]")
            continue
        console.rule(f"[bold][{i}/{len(stages)}] {st.name}[/]: physavatar {' '.join(st.args)}")
        t0 = time.time()
        proc = subprocess.run([sys.executable, "-m", "physavatar.cli", *st.args], env=env)
        secs = round(time.time() - t0, 1)
        if proc.returncode == 130:
            raise KeyboardInterrupt
        if proc.returncode != 0:
            record[st.name] = {"args": st.args, "seconds": secs, "status": f"failed ({proc.returncode})"}
            write_json_atomic(rec_path, record)
            raise PhysavatarError(out / st.name, f"stage {st.name!r} failed (exit code {proc.returncode}); "
                                  f"fix the cause and run again to resume")
        record[st.name] = {"args": st.args, "seconds": secs, "status": "ok"}
        write_json_atomic(rec_path, record)
    record["_total_seconds_this_run"] = round(time.time() - t_all, 1)
    write_json_atomic(rec_path, record)
    return record


def write_report(out: str | Path) -> Path:
    """OUT/report.md: metrics, textures before/after, novel views, loss plots, stage wall times."""
    from ..files import write_text_atomic

    out = Path(out)
    rec = read_json(out / "run.json") if (out / "run.json").exists() else {}
    L = ["# physavatar run", ""]
    ev = out / "evaluate" / "report.md"
    if ev.exists():
        body = ev.read_text().split("\n", 1)[1]  # drop its title
        L += ["## Metrics", body.replace("\n## ", "\n### "), ""]
    pics = [("Texture before inverse rendering (Gaussian colours)", "appearance/texture_init.png"),
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
    times = [(k, v) for k, v in rec.items() if isinstance(v, dict) and "seconds" in v]
    if times:
        L += ["## Wall time per stage (2-core CPU)", "", "| stage | seconds | status |", "| --- | --- | --- |"]
        L += [f"| {k} | {v['seconds']} | {v.get('status', '')} |" for k, v in times]
        L += [f"| **total** | {sum(v['seconds'] for _, v in times):.1f} | |", ""]
    path = out / "report.md"
    write_text_atomic(path, "\n".join(L) + "\n")
    return path
