"""``physavatar run CAPTURE OUT``: the whole pipeline, in process, resumable.

(prepare, when the capture is unprepared: no body.npz or labelled template) -> track ->
fit-physics -> fit-appearance -> build-avatar -> animate (held-out motion) -> render -> relight ->
export -> evaluate (with an oracle fit beside, for a capture whose material no file gives). :func:`plan` lists the stages as :class:`Step` s: a stage function
(``run(inputs..., out=, config=, progress=)`` of its module in ``stages/``), its inputs and its
config. :func:`run` calls them in order, each writing ``OUT/<stage>/``.

What is skipped: a stage whose final output exists and whose hash (its config and its inputs:
the capture's files by path, size and modification time, or the hashes of the stages it reads
from, and the content of a file its config names, ``--motion``; :func:`stages.base.stage_hash`)
equals the one recorded in ``OUT/run.json`` when it last finished. So an interrupted run resumes
where it stopped, a changed setting re-runs that stage and everything downstream of it, and the
stages' own resume logic (tracking per frame, appearance checkpoints) picks up inside a stage.

What runs beside: stages marked ``background`` need nothing from the stages between them and their
consumers; one scheduler starts them in a child process on a spare core (``PHYSAVATAR_WORKERS=1``,
output to ``OUT/<stage>/stage.log``) while the next stages run here, and a stage that needs one of
them waits for it. The evaluation's reference simulations run beside tracking (single-threaded),
fit-appearance (Mitsuba) beside fit-physics. On a one-core machine everything runs in line.
"""

from __future__ import annotations

import importlib
import inspect
import logging
import multiprocessing
import os
import time
import traceback
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from .errors import PhysavatarError
from .files import content_key, read_json, write_json_atomic
from .parallel import default_workers
from .stages.base import camera_list, fingerprint, option, stage_hash, to_dict


@dataclass
class Step:
    """One stage of a run. ``fn``: ``"module:function"`` (importable in a child process);
    ``inputs``: keyword arguments that are inputs (paths, or names of earlier steps given as
    ``("step", NAME)`` whose folder ``OUT/NAME`` is passed and whose hash enters this one's);
    ``done_file``: relative to ``OUT/<name>`` (``out_file`` when the stage writes one file);
    a step waits for the background steps it reads from (:func:`needs`)."""

    name: str
    fn: str
    config: Any
    inputs: dict = field(default_factory=dict)
    done_file: str = ""
    out_file: str | None = None  # the stage's ``out`` is OUT/<name>/<out_file> instead of the folder
    background: bool = False
    command: list[str] = field(default_factory=list)  # the equivalent command line, for the report
    # files the config names (animate's --motion): not passed as inputs, but their content enters the hash
    files: dict = field(default_factory=dict)

    def out(self, root: Path) -> Path:
        return root / self.name / self.out_file if self.out_file else root / self.name


def _positive(v):
    return None if v >= 1 else "must be at least 1"


def _odd_positive(v):
    return None if v >= 1 and v % 2 == 1 else "use an odd number of draws (the row is the median draw)"


def _passes(v):
    return None if v in (1, 2) else "1 (track once) or 2 (track again with the fitted material)"


def evaluate_random_draws() -> int:
    from .stages.evaluate import RANDOM_DRAWS

    return RANDOM_DRAWS


@dataclass(frozen=True)
class RunConfig:
    """``physavatar run``'s settings (saved in ``OUT/run.json``)."""

    quick: bool = option(False, "smaller budgets for every stage (tests, previews)")
    track_frames: int | None = option(None, "track only the first N frames", check=_positive)
    eval_frames: int | None = option(None, "animate / evaluate only the first N held-out frames", check=_positive)
    random_draws: int = option(evaluate_random_draws(), "random materials the evaluation of a synthetic capture "
                               "simulates (odd; the row is the median draw)", check=_odd_positive)
    motion: str | None = option(None, "motion to animate (built-in name, .bvh, .npz); default: the synthetic "
                                "capture's held-out motion (then also evaluated), else 'dance'")
    holdout: tuple[str, ...] | None = option(None, "cameras held out of tracking and scored by evaluate, CAM,CAM "
                                             "('' for none; default: two when the capture has six or more)",
                                             parse=camera_list)
    track_passes: int = option(1, "2: track again with the material fit-physics found on the first pass "
                               "(the paper's loop; the appearance and evaluation then read the second "
                               "pass; docs/tracking.md)", check=_passes)


def _resolve(value, out: Path):
    if isinstance(value, tuple) and len(value) == 2 and value[0] == "step":
        return out / value[1]
    return value


def plan(capture: Path, out: Path, cfg: RunConfig = RunConfig()) -> list[Step]:
    """The stages of a run, in order (see the module docstring)."""
    from .stages import animate, appearance, avatar, evaluate, export, physics, render, track

    from .capture import is_unprepared

    capture = Path(capture)
    held_file = capture / "ground_truth" / "heldout" / "motion.npz"
    motion = cfg.motion or (str(held_file) if held_file.exists() else "dance")
    # An unprepared capture (straight from `physavatar import`) is prepared first; every other
    # stage reads the prepared capture (OUT/prepare), which keeps the ground truth of a synthetic one.
    unprepared = is_unprepared(capture)
    cap = {"capture": ("step", "prepare") if unprepared else capture}
    # The tracking that appearance and evaluate read: the first pass, or with --track-passes 2 the
    # second, whose physics prediction uses the material fitted on the first (the paper's loop).
    tracked = ("step", "retrack" if cfg.track_passes == 2 else "track")
    # fit-appearance (Mitsuba, multi-threaded) runs beside fit-physics (single-threaded
    # simulations): both need only the tracking (with two passes, beside the later stages).
    appear = Step("appearance", "physavatar.stages.appearance:run", appearance.pipeline_config(cfg.quick),
                  cap | {"tracked": tracked}, "texture.png", background=True)
    steps = [
        Step("track", "physavatar.stages.track:run", track.pipeline_config(cfg.track_frames, cfg.holdout), cap, "tracked.npz"),
        *([appear] if cfg.track_passes == 1 else []),
        Step("physics", "physavatar.stages.physics:run", physics.pipeline_config(cfg.quick),
             {"source": ("step", "track")}, "material.json"),
        *([Step("retrack", "physavatar.stages.track:run", track.second_pass_config(cfg.track_frames, cfg.holdout),
                cap | {"material": ("step", "physics")}, "tracked.npz"), appear] if cfg.track_passes == 2 else []),
        Step("avatar", "physavatar.stages.avatar:run", avatar.AvatarConfig(),
             cap | {"material": ("step", "physics"), "appearance": ("step", "appearance")}, "avatar.json"),
        Step("animate", "physavatar.stages.animate:run", animate.pipeline_config(motion, cfg.eval_frames),
             {"avatar": ("step", "avatar")}, "sequence.json",
             files={"motion": cfg.motion} if cfg.motion and Path(cfg.motion).is_file() else {}),
        Step("render", "physavatar.stages.render:run", render.pipeline_config("fitted", cfg.quick),
             {"sequence": ("step", "animate")}, "render.json"),
        Step("relight", "physavatar.stages.render:run", render.pipeline_config("sky", cfg.quick),
             {"sequence": ("step", "animate")}, "render.json"),
        Step("export", "physavatar.stages.export:run", export.ExportConfig(format="usd"),
             {"sequence": ("step", "animate")}, "avatar.usdc", out_file="avatar.usdc"),
        Step("export-glb", "physavatar.stages.export:run", export.ExportConfig(format="glb"),
             {"sequence": ("step", "animate")}, "avatar.glb", out_file="avatar.glb"),
    ]
    # Evaluation needs ground truth: synthetic captures only.
    if held_file.exists() and (capture / "ground_truth" / "heldout" / "meshes.npz").exists():
        # The true- and random-material rows need nothing fitted: simulated on the second core
        # while tracking (single-threaded) runs on the first.
        # The random draws get the thickness the fit will use (given, or estimated on the template).
        # ... and the rest shape its material will record (Material.rest_shape)
        fit_cfg = physics.pipeline_config(cfg.quick)
        refs_cfg = evaluate.ReferencesConfig(frames=cfg.eval_frames, contact_offset=fit_cfg.contact_offset,
                                             rest_shape=fit_cfg.rest_shape, rest_friction=fit_cfg.rest_friction,
                                             random_draws=cfg.random_draws)
        steps.insert(0, Step("references", "physavatar.stages.evaluate:run_references", refs_cfg, cap,
                             "references.json", background=True))
        inputs = cap | {"avatar": ("step", "avatar"), "tracked": tracked, "references": ("step", "references")}
        if not (capture / "ground_truth" / "material.json").exists() and \
                (capture / "ground_truth" / "meshes.npz").exists():
            # Another simulator's garment: no true material in this one's terms. The oracle row is
            # the material fitted on the true meshes (the model gap without tracking error).
            steps.insert(1, Step("oracle", "physavatar.stages.physics:run", physics.pipeline_config(cfg.quick),
                                 {"source": cap["capture"]}, "material.json", background=True))
            inputs["oracle"] = ("step", "oracle")
        if cfg.motion is None:  # the animate stage ran the held-out motion: reuse it
            inputs["sequence"] = ("step", "animate")
        steps.append(Step("evaluate", "physavatar.stages.evaluate:run",
                          evaluate.EvaluateConfig(frames=cfg.eval_frames, random_draws=cfg.random_draws), inputs,
                          "metrics.json"))
    elif _holds_out(capture, cfg.holdout):
        # Any capture: the cameras tracking held out are scored (the tracked meshes, textured and lit).
        steps.append(Step("evaluate", "physavatar.stages.evaluate:run", evaluate.EvaluateConfig(),
                          cap | {"avatar": ("step", "avatar"), "tracked": tracked}, "metrics.json"))
    if unprepared:  # first of all: even the background steps read its output
        from .stages import prepare

        steps.insert(0, Step("prepare", "physavatar.stages.prepare:run", prepare.PrepareConfig(), {"capture": capture},
                             "prepare.json"))
    for st in steps:
        st.command = _command(st, out)
    return steps


def _holds_out(capture: Path, holdout: tuple[str, ...] | None) -> bool:
    """Whether tracking holds cameras out of ``capture`` (the given ones, else the default rule)."""
    from .stages.track.stage import default_holdout

    if holdout is not None:
        return bool(holdout)
    try:
        names = [c["name"] for c in read_json(capture / "cameras.json")]
    except (PhysavatarError, KeyError, TypeError):
        return False  # an unreadable capture fails in its first stage, with its own message
    return bool(default_holdout(names))


def _command(st: Step, out: Path) -> list[str]:
    """The ``physavatar`` command line equivalent to a step (shown in the report)."""
    from .stages.base import to_argv, unflagged_changes

    if st.name == "prepare":  # physavatar prepare CAPTURE OUT
        return ["prepare", str(st.inputs["capture"]), str(st.out(out))] + to_argv(st.config)
    names = {"track": "track", "retrack": "track", "appearance": "fit-appearance", "physics": "fit-physics", "avatar": "build-avatar",
             "animate": "animate", "render": "render", "relight": "render", "export": "export",
             "export-glb": "export", "references": "reference-sims", "evaluate": "evaluate", "oracle": "fit-physics"}
    args = [names.get(st.name, st.name)]
    first, *rest = list(st.inputs.items()) or [(None, None)]
    if first[0] is not None:
        args.append(str(_resolve(first[1], out)))
    args += ["--out", str(st.out(out))]
    for k, v in rest:
        args += [f"--{k}", str(_resolve(v, out))]
    args += to_argv(st.config)
    extra = unflagged_changes(st.config)
    if extra:  # settings a preset changes that have no flag of their own
        args += ["#"] + [f"{k}={v}" for k, v in extra.items()]
    return args


def step_hash(st: Step, out: Path, record: dict) -> str:
    """The step's hash: its config and inputs, an earlier step's input by that step's hash in
    ``record`` (``run.json``'s entries; only those of the steps it reads from are needed), and
    the content (files.content_key) of the files its config names (``Step.files``)."""
    inputs = {f"file:{k}": content_key(Path(v)) for k, v in st.files.items()}
    for k, v in st.inputs.items():
        if isinstance(v, tuple) and v[:1] == ("step",):
            inputs[k] = {"step": v[1], "hash": record.get(v[1], {}).get("hash")}
        elif isinstance(v, (str, Path)) and Path(v).exists():
            inputs[k] = Path(v)
        else:
            inputs[k] = v
    return stage_hash(st.config, inputs)


def _call(st: Step, out: Path, progress, say=None) -> Any:
    mod, fn = st.fn.split(":")
    func = getattr(importlib.import_module(mod), fn)
    kwargs = {k: _resolve(v, out) for k, v in st.inputs.items()}
    if say is not None and "say" in inspect.signature(func).parameters:
        kwargs["say"] = say  # a stage's notes (fit-physics: the start state, the proxy, each iteration)
    return func(**kwargs, out=st.out(out), config=st.config, progress=progress)


def needs(st: Step) -> list[str]:
    """The steps ``st`` reads from (its ``("step", NAME)`` inputs): it waits for them, and their
    hashes enter its own."""
    return list(dict.fromkeys(v[1] for v in st.inputs.values() if isinstance(v, tuple) and v[:1] == ("step",)))


def upstream(st: Step, out: Path, record: dict) -> dict:
    """The final files of the steps ``st`` reads from as they are now: name -> their
    :func:`~stages.base.fingerprint` (None for an entry that does not name its file)."""
    files = {n: record.get(n, {}).get("output") for n in needs(st)}
    return {n: fingerprint(out / f) if f else None for n, f in files.items()}


def is_done(st: Step, out: Path, prev: dict, h: str, up: dict | None = None) -> bool:
    """Finished earlier with the same hash (its final output still there) and, where its entry
    records them, from the same outputs of the steps it reads (``up``: :func:`upstream`; one
    re-made since, e.g. by hand with other options, runs this step again): skipped."""
    return (out / st.name / st.done_file).exists() and prev.get("hash") == h and prev.get("status") == "ok" \
        and (up is None or "upstream" not in prev or prev["upstream"] == up)


def entry(st: Step, h: str, status: str, secs: float, *, background: bool = False, error: str | None = None,
          up: dict | None = None) -> dict:
    """The step's entry in ``run.json`` (``output``: its final file, relative to OUT; ``upstream``:
    :func:`upstream` when it ran)."""
    return ({"hash": h, "seconds": round(secs, 1), "status": status, "command": st.command,
             "config": to_dict(st.config), "output": f"{st.name}/{st.done_file}"}
            | ({"upstream": up} if up is not None else {}) | ({"background": True} if background else {})
            | ({"error": error} if error else {}))


def execute(st: Step, out: Path, h: str, *, progress=False, say=None, up: dict | None = None) -> dict:
    """Call the step's stage function; returns its ``run.json`` entry (``up``: :func:`upstream`
    before it ran). A stage's :class:`PhysavatarError` (bad input) gives status ``failed`` with its
    ``error``; anything else (a bug, Ctrl-C) propagates."""
    (out / st.name).mkdir(parents=True, exist_ok=True)
    t0 = time.time()
    try:
        _call(st, out, progress, say)
    except PhysavatarError as e:
        return entry(st, h, "failed", time.time() - t0, error=str(e), up=up)
    return entry(st, h, "ok", time.time() - t0, up=up)


@dataclass
class StepResult:
    """What :func:`run_step` gives back: the step's ``run.json`` entry (the previous one when skipped)."""

    name: str
    entry: dict
    skipped: bool = False

    @property
    def ok(self) -> bool:
        return self.entry.get("status") == "ok"


def run_step(st: Step, out: Path, record: dict, *, progress=False) -> StepResult:
    """Run one step of a run into ``out``, or skip it when it finished earlier with the same hash.
    ``record``: ``run.json``'s entries, at least those of the steps it reads from and its own
    previous one. Whoever calls it merges the returned entry into ``run.json`` (:func:`run` in
    order; a batch's Ray driver as tasks finish, in any order)."""
    h = step_hash(st, out, record)
    prev = record.get(st.name, {})
    up = upstream(st, out, record)
    if is_done(st, out, prev, h, up):
        return StepResult(st.name, prev, skipped=True)
    return StepResult(st.name, execute(st, out, h, progress=progress, up=up))


def _child(st: Step, out: Path, h: str, log_path: Path, conn, up: dict | None = None) -> None:
    """A background stage in its own process (:func:`execute`): output to its log, its ``run.json``
    entry through ``conn``."""
    os.environ["PHYSAVATAR_WORKERS"] = "1"  # one core: the other runs the next stages
    fd = os.open(log_path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
    os.dup2(fd, 1)
    os.dup2(fd, 2)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s: %(message)s", force=True)
    try:
        e = execute(st, out, h, up=up)
        if e.get("error"):
            print(f"error: {e['error']}", flush=True)
        conn.send(("done", e, time.time()))
    except KeyboardInterrupt:
        conn.send(("interrupted", None, time.time()))
    except BaseException:  # noqa: BLE001 - reported to the parent, which names the log
        traceback.print_exc()
        conn.send(("done", entry(st, h, "failed", 0.0, error="an unexpected error (traceback in the log)"),
                   time.time()))
    finally:
        conn.close()


@dataclass
class _Running:
    step: Step
    proc: Any
    conn: Any
    t0: float
    hash: str


def run(capture: str | Path, out: str | Path, cfg: RunConfig = RunConfig(), *, only: list[str] | None = None,
        say=print) -> dict:
    """Run (or resume) every stage; returns the run record (per-stage hash, seconds and status).

    ``say(text)`` prints one line (the CLI passes its console's print)."""
    capture, out = Path(capture), Path(out)
    if not capture.is_dir():
        raise PhysavatarError(capture, "capture folder not found")
    out.mkdir(parents=True, exist_ok=True)
    rec_path = out / "run.json"
    record = read_json(rec_path) if rec_path.exists() else {}
    record["_capture"] = str(capture)
    record["_config"] = to_dict(cfg)
    steps = plan(capture, out, cfg)
    cores = default_workers(64)
    t_all = time.time()
    running: dict[str, _Running] = {}
    skipped: list[str] = []
    ctx = multiprocessing.get_context("spawn")

    def save(st: Step, e: dict) -> None:
        record[st.name] = e
        write_json_atomic(rec_path, record)

    def finish(name: str) -> None:
        """Wait for background stage ``name`` and record it; raise if it failed."""
        r = running.pop(name)
        if r.proc.is_alive() and not r.conn.poll():
            say(f"waiting for {name} (running beside since {time.time() - r.t0:.0f} s; "
                f"log: {out / name / 'stage.log'})")
        try:
            kind, e, t_end = r.conn.recv()
        except EOFError:  # died without a word (killed)
            kind, e, t_end = "done", None, time.time()
        r.proc.join()
        if kind == "interrupted":
            raise KeyboardInterrupt
        e = e or entry(r.step, r.hash, "failed", 0.0, error="the process ended unexpectedly")
        # its wall time beside the others, process start included
        save(r.step, e | {"seconds": round(t_end - r.t0, 1), "background": True})
        ok = e["status"] == "ok"
        say(f"{name} (beside the other stages): {'done' if ok else 'failed'} after {record[name]['seconds']} s")
        if not ok:
            raise PhysavatarError(out / name / "stage.log", f"stage {name!r} failed: {e['error']}; fix the cause "
                                  "and run again to resume")

    try:
        for i, st in enumerate(steps, 1):
            if only and st.name not in only:
                continue
            for name in [n for n, r in running.items() if not r.proc.is_alive() or r.conn.poll()]:
                finish(name)  # ended meanwhile: its core is free again
            for name in needs(st):  # before its hash: theirs enter it
                if name in running:
                    finish(name)
            h = step_hash(st, out, record)
            prev = record.get(st.name, {})
            up = upstream(st, out, record)
            if is_done(st, out, prev, h, up):
                say(f"[{i}/{len(steps)}] {st.name}: done earlier ({prev.get('seconds', '?')} s), skipped")
                skipped.append(st.name)
                continue
            if st.background and len(running) < cores - 1:
                (out / st.name).mkdir(parents=True, exist_ok=True)
                parent, child = ctx.Pipe(duplex=False)
                proc = ctx.Process(target=_child, args=(st, out, h, out / st.name / "stage.log", child, up),
                                   daemon=False)
                proc.start()
                child.close()
                running[st.name] = _Running(st, proc, parent, time.time(), h)
                say(f"[{i}/{len(steps)}] {st.name}: physavatar {' '.join(st.command)}  (beside the next stages on "
                    f"another core; log: {out / st.name / 'stage.log'})")
                continue
            say(f"[{i}/{len(steps)}] {st.name}: physavatar {' '.join(st.command)}")
            e = execute(st, out, h, progress=True, say=say, up=up)
            save(st, e)
            if e["status"] != "ok":
                raise PhysavatarError(None, f"stage {st.name!r} failed: {e['error']}; fix the cause and run again "
                                      "to resume")
        for name in list(running):
            finish(name)
    finally:
        for r in running.values():  # interrupted or failed: stop what runs beside
            r.proc.terminate()
            r.proc.join()
    record["_total_seconds_this_run"] = round(time.time() - t_all, 1)
    record["_skipped_this_run"] = skipped
    write_json_atomic(rec_path, record)
    return record

