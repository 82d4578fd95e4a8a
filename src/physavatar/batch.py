"""``physavatar batch CAPTURES... --out OUT``: :func:`pipeline.run` for many captures, locally or on Ray.

Every capture runs into ``OUT/<name>/`` (its folder's name, made unique) with ``run``'s own resume
rules: a stage is skipped when it finished earlier with the same hash, so a killed batch started
again skips what finished and a capture that failed runs again from the stage that failed. A
capture that fails is reported with its error; the others go on. At the end :func:`summarize`
reads each capture's ``run.json`` and ``evaluate/metrics.json`` into ``OUT/batch.json`` and
``OUT/batch.md`` (docs/batch.md).

Local (:func:`run_local`): one capture at a time in this process, or ``jobs`` captures side by side,
each in its own process with ``PHYSAVATAR_WORKERS`` = cores / jobs and its output in
``OUT/<name>/batch.log``.

Ray (:func:`run_ray`): every stage of every capture is one Ray task declaring its CPUs (and a GPU
on a cluster that has them) whose arguments include the results of the stages it reads from
(:func:`pipeline.needs`), so Ray starts it when they are done and spreads independent stages of
all captures over the cluster. A task runs :func:`pipeline.run_step` on the shared ``OUT`` folder
and returns only the stage's ``run.json`` entry (hash, seconds, status); this driver merges the
entries into each capture's ``run.json`` as tasks finish, in whatever order.
"""

from __future__ import annotations

import glob
import json
import os
import time
import traceback
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import dataclass
from pathlib import Path

from .errors import PhysavatarError
from .files import read_json, write_json_atomic, write_text_atomic
from .parallel import default_workers
from .pipeline import RunConfig, Step, StepResult, needs, plan, run_step
from .stages.base import to_dict

RAY_INSTALL = "pip install 'physavatar[ray]' (or: pip install 'ray>=2.9')"
# CPUs a stage's Ray task declares (1 when not listed): Mitsuba's inverse rendering is multi-threaded,
# everything else single-threaded (tracking at one thread, the simulator serial).
STAGE_CPUS = {"appearance": 2}
# Stages that use a CUDA device when there is one (gsplat, Mitsuba's cuda variant).
GPU_STAGES = ("track", "retrack", "appearance", "render", "relight")


@dataclass(frozen=True)
class Capture:
    """One capture of a batch: its folder and its output's name (``OUT/<name>``)."""

    name: str
    path: Path


def collect(args: list[str]) -> list[Capture]:
    """The captures named by ``args``: folders, glob patterns (the folders they match) or ``.txt``
    lists (one folder or pattern a line, ``#`` comments, relative to the list's folder). The same
    folder named twice is kept once; two folders of the same name get ``name``, ``name-2``, ..."""
    paths: list[Path] = []

    def add(text: str, base: Path | None = None) -> None:
        p = Path(text).expanduser()
        if base is not None and not p.is_absolute():
            p, text = base / p, str(base / p)
        if p.suffix == ".txt" and p.is_file():
            for line in p.read_text().splitlines():
                line = line.split("#", 1)[0].strip()
                if line:
                    add(line, p.parent)
        elif glob.has_magic(text) and not p.exists():
            found = sorted(Path(m) for m in glob.glob(text) if Path(m).is_dir())
            if not found:
                raise PhysavatarError(text, "matches no folder")
            paths.extend(found)
        else:
            paths.append(p)  # a missing folder is reported as that capture's failure

    for a in args:
        add(str(a))
    seen, caps, used = set(), [], set()
    for p in paths:
        key = os.path.realpath(p)
        if key in seen:
            continue
        seen.add(key)
        base = Path(key).name or "capture"
        name, k = base, 2
        while name in used:
            name, k = f"{base}-{k}", k + 1
        used.add(name)
        caps.append(Capture(name, p))
    if not caps:
        raise PhysavatarError(None, "no captures given")
    return caps


def default_jobs(n_captures: int) -> int:
    """Captures side by side on this machine: one per core, at most the number of captures. (One
    capture alone leaves its second core idle most of the time: tracking, single-threaded, is
    most of a run; two captures in line on one core each finish twice as many per hour.)"""
    return max(1, min(n_captures, default_workers(1 << 16)))


# ---- local ------------------------------------------------------------------------------------

def _run_capture(cap: Capture, out: Path, cfg: RunConfig, say=print) -> dict:
    """``pipeline.run`` + the report for one capture; a failure becomes the result's ``error``."""
    from .pipeline import run
    from .report import write_report

    t0 = time.time()
    res = {"name": cap.name, "capture": str(cap.path), "status": "ok", "error": None}
    try:
        rec = run(cap.path, out / cap.name, cfg, say=say)
        write_report(out / cap.name)
        res["skipped"] = rec.get("_skipped_this_run", [])
    except PhysavatarError as e:
        res |= {"status": "failed", "error": str(e)}
    except Exception as e:  # noqa: BLE001 - a bug in one capture must not stop the others
        traceback.print_exc()
        res |= {"status": "failed", "error": f"unexpected {type(e).__name__}: {e}"}
    res["seconds"] = round(time.time() - t0, 1)
    return res


def _run_capture_child(cap: Capture, out: Path, cfg: RunConfig, workers: int) -> dict:
    """:func:`_run_capture` in a process of its own: ``workers`` cores, output to ``batch.log``."""
    import logging
    import sys

    os.environ["PHYSAVATAR_WORKERS"] = str(workers)
    (out / cap.name).mkdir(parents=True, exist_ok=True)
    fd = os.open(out / cap.name / "batch.log", os.O_WRONLY | os.O_CREAT | os.O_APPEND, 0o644)
    sys.stdout.flush()
    sys.stderr.flush()
    os.dup2(fd, 1)
    os.dup2(fd, 2)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s: %(message)s", force=True)
    return _run_capture(cap, out, cfg, say=lambda text: print(text, flush=True))


def run_local(caps: list[Capture], out: Path, cfg: RunConfig, *, jobs: int | None = None, say=print) -> list[dict]:
    """Every capture on this machine: in this process when ``jobs`` is 1, else ``jobs`` at a time
    in processes of their own (default :func:`default_jobs`); returns one result per capture."""
    import multiprocessing

    jobs = default_jobs(len(caps)) if jobs is None else max(1, min(jobs, len(caps)))
    if jobs == 1:
        results = []
        for i, cap in enumerate(caps, 1):
            say(f"== [{i}/{len(caps)}] {cap.name}: {cap.path} -> {out / cap.name}")
            r = _run_capture(cap, out, cfg, say=say)
            say(_result_line(r))
            results.append(r)
        return results
    workers = max(1, default_workers(1 << 16) // jobs)
    say(f"{len(caps)} captures, {jobs} side by side with {workers} core(s) each; each one's output in "
        f"{out}/<name>/batch.log")
    by_name: dict[str, dict] = {}
    with ProcessPoolExecutor(jobs, mp_context=multiprocessing.get_context("spawn"), max_tasks_per_child=1) as ex:
        futs = {ex.submit(_run_capture_child, cap, out, cfg, workers): cap for cap in caps}
        try:
            for f in as_completed(futs):
                cap = futs[f]
                try:
                    r = f.result()
                except Exception as e:  # noqa: BLE001 - the process died (killed, out of memory)
                    r = {"name": cap.name, "capture": str(cap.path), "status": "failed",
                         "error": f"its process ended unexpectedly ({type(e).__name__}); see "
                                  f"{out / cap.name / 'batch.log'}"}
                by_name[cap.name] = r
                say(_result_line(r))
        except BaseException:
            ex.shutdown(wait=False, cancel_futures=True)
            raise
    return [by_name[c.name] for c in caps]


def _result_line(r: dict) -> str:
    if r["status"] == "ok":
        skipped = r.get("skipped") or []
        extra = f" ({len(skipped)} stages done earlier, skipped)" if skipped else ""
        return f"{r['name']}: done in {r.get('seconds', 0):.0f} s{extra}"
    return f"{r['name']}: FAILED: {r['error']}"


# ---- Ray --------------------------------------------------------------------------------------

def import_ray():
    """The ``ray`` module, or a clear error saying how to install it."""
    try:
        import ray
    except ImportError:
        raise PhysavatarError(None, f"--ray needs Ray, an optional extra: {RAY_INSTALL}") from None
    return ray


def _stage_task(st: Step, out: Path, prev: dict, workers: int, *deps: StepResult) -> StepResult:
    """One stage in a Ray worker: run (or skip) it once the stages it reads from are done; output
    to ``OUT/<stage>/stage.log``. Never raises: a failure is the returned entry's ``error``.

    Ray is active in the task, so the stage's independent simulations (``parallel.run_jobs``: synth's
    motions, the reference / evaluation materials; fit_fd's finite differences) are sub-tasks of one
    CPU each; while the stage waits for them its own CPU is released to them (Ray lends a blocked
    worker's CPUs), so a full cluster of one-CPU stage tasks does not deadlock."""
    import sys

    bad = [d.name for d in deps if not d.ok]
    if bad:
        return StepResult(st.name, {"status": "not run", "error": f"needs {', '.join(bad)}, which did not finish"})
    os.environ["PHYSAVATAR_WORKERS"] = str(workers)
    (out / st.name).mkdir(parents=True, exist_ok=True)
    sys.stdout.flush()
    sys.stderr.flush()
    saved = os.dup(1), os.dup(2)
    fd = os.open(out / st.name / "stage.log", os.O_WRONLY | os.O_CREAT | os.O_APPEND, 0o644)
    os.dup2(fd, 1)
    os.dup2(fd, 2)
    try:
        return run_step(st, out, {d.name: d.entry for d in deps} | {st.name: prev}, progress=False)
    except BaseException as e:  # noqa: BLE001 - reported to the driver, traceback in the log
        traceback.print_exc()
        return StepResult(st.name, {"status": "failed", "error": f"unexpected {type(e).__name__}: {e} "
                                                                 f"(traceback in {out / st.name / 'stage.log'})"})
    finally:
        sys.stdout.flush()
        sys.stderr.flush()
        os.dup2(saved[0], 1)
        os.dup2(saved[1], 2)
        for f in (fd, *saved):
            os.close(f)


def run_ray(caps: list[Capture], out: Path, cfg: RunConfig, *, address: str | None = None, cpus: int | None = None,
            say=print) -> list[dict]:
    """Every stage of every capture as a Ray task: an embedded local Ray (``address`` None or
    ``"local"``; ``cpus``: its CPUs, default all) or the cluster at ``address`` (``"auto"``, or
    ``ray://host:10001``). ``OUT`` must be on storage every node sees."""
    ray = import_ray()
    started = False
    if not ray.is_initialized():
        if address in (None, "", "local") and not os.environ.get("RAY_ADDRESS"):
            ray.init(num_cpus=cpus, include_dashboard=False, log_to_driver=False)
        elif address in (None, "", "local"):  # RAY_ADDRESS: that cluster
            ray.init(log_to_driver=False)
        else:
            ray.init(address=address, log_to_driver=False)
        started = True
    try:
        return _ray_batch(ray, caps, out, cfg, say)
    finally:
        if started:
            ray.shutdown()


def _ray_batch(ray, caps: list[Capture], out: Path, cfg: RunConfig, say) -> list[dict]:
    from .report import write_report

    nodes = [n for n in ray.nodes() if n.get("Alive")]
    node_cpus = max([int(n["Resources"].get("CPU", 1)) for n in nodes] or [1])
    gpus = ray.cluster_resources().get("GPU", 0) > 0
    say(f"Ray: {len(nodes)} node(s), {ray.cluster_resources().get('CPU', 0):.0f} CPUs"
        f"{', GPUs' if gpus else ''}; {len(caps)} captures")
    task = ray.remote(_stage_task)
    t0 = time.time()
    results: dict[str, dict] = {}
    records: dict[str, dict] = {}
    pending: dict = {}  # ObjectRef -> (capture name, step)
    left: dict[str, int] = {}
    for cap in caps:
        dest = out / cap.name
        res = {"name": cap.name, "capture": str(cap.path), "status": "ok", "error": None, "skipped": []}
        results[cap.name] = res
        if not cap.path.is_dir():
            res |= {"status": "failed", "error": f"{cap.path}: capture folder not found"}
            say(_result_line(res))
            continue
        dest.mkdir(parents=True, exist_ok=True)
        rec = read_json(dest / "run.json") if (dest / "run.json").exists() else {}
        records[cap.name] = rec | {"_capture": str(cap.path), "_config": to_dict(cfg)}
        refs: dict[str, object] = {}
        steps = plan(cap.path, dest, cfg)
        for st in steps:
            c = min(STAGE_CPUS.get(st.name, 1), node_cpus)
            opts = {"num_cpus": c, "name": f"{cap.name}/{st.name}"}
            if gpus and st.name in GPU_STAGES:
                opts["num_gpus"] = 1
            ref = task.options(**opts).remote(st, dest, rec.get(st.name, {}), c, *[refs[n] for n in needs(st)])
            refs[st.name] = ref
            pending[ref] = (cap.name, st)
        left[cap.name] = len(steps)
        res["t0"] = time.time()
    try:
        while pending:
            done, _ = ray.wait(list(pending), num_returns=1)
            for ref in done:
                name, st = pending.pop(ref)
                r: StepResult = ray.get(ref)
                res, rec, dest = results[name], records[name], out / name
                if r.skipped:
                    res["skipped"].append(st.name)
                elif r.entry.get("status") != "not run":
                    rec[st.name] = r.entry
                    write_json_atomic(dest / "run.json", rec)
                    say(f"{name}/{st.name}: {r.entry['status']} after {r.entry.get('seconds', '?')} s")
                if not r.ok and res["status"] == "ok":
                    res |= {"status": "failed", "error": f"stage {st.name!r} failed: {r.entry.get('error')}"}
                left[name] -= 1
                if not left[name]:
                    res["seconds"] = round(time.time() - res.pop("t0"), 1)
                    rec["_total_seconds_this_run"] = res["seconds"]
                    rec["_skipped_this_run"] = res["skipped"]
                    write_json_atomic(dest / "run.json", rec)
                    write_report(dest)
                    say(_result_line(res))
    except BaseException:
        for ref in pending:
            ray.cancel(ref, force=True)
        raise
    say(f"all {len(caps)} captures in {time.time() - t0:.0f} s")
    return [results[c.name] for c in caps]


# ---- summary ----------------------------------------------------------------------------------

def _metrics(out: Path) -> dict:
    """The key numbers of a capture's run: ``evaluate/metrics.json`` (synthetic captures) and
    the fitted material."""
    m = {}
    p = out / "evaluate" / "metrics.json"
    if p.exists():
        ev = read_json(p)
        rows = ev.get("rows", {})
        for row, key in (("estimated material", "garment_chamfer_x1e3"), ("true material", "garment_chamfer_true_x1e3"),
                         ("LBS", "garment_chamfer_lbs_x1e3")):
            v = rows.get(row, {}).get("garment", {}).get("chamfer_x1e3")
            if v is not None:
                m[key] = v
        for part, r in ev.get("tracking", {}).items():
            if isinstance(r, dict) and "mean_mm" in r:
                m[f"tracking_{part}_mm"] = r["mean_mm"]
        app = ev.get("appearance", {})
        for k in ("psnr", "ssim", "lpips"):
            if isinstance(app.get(k), (int, float)):
                m[k] = app[k]
    p = out / "physics" / "material.json"
    if p.exists():
        mat = read_json(p).get("material", {})
        for k in ("stretch_stiffness", "bend_stiffness", "density"):
            if isinstance(mat.get(k), (int, float)):
                m[k] = mat[k]
    return m


def summarize(results: list[dict], out: Path, cfg: RunConfig, *, mode: str, seconds: float) -> dict:
    """``OUT/batch.json`` and ``OUT/batch.md`` from the results and each capture's ``run.json``
    and metrics; returns the batch record."""
    rows = []
    for r in results:
        dest = out / r["name"]
        rec = read_json(dest / "run.json") if (dest / "run.json").exists() else {}
        stages = {k: v for k, v in rec.items() if isinstance(v, dict) and "seconds" in v}
        rows.append({**{k: v for k, v in r.items() if k != "t0"},
                     "output": r["name"],
                     "report": f"{r['name']}/report.md" if (dest / "report.md").exists() else None,
                     "stage_seconds": {k: v["seconds"] for k, v in stages.items()},
                     "stage_status": {k: v["status"] for k, v in stages.items()},
                     "metrics": _metrics(dest)})
    batch = {"mode": mode, "config": to_dict(cfg), "seconds": round(seconds, 1),
             "ok": sum(r["status"] == "ok" for r in rows), "failed": sum(r["status"] != "ok" for r in rows),
             "captures": rows}
    write_json_atomic(out / "batch.json", batch)
    write_text_atomic(out / "batch.md", batch_markdown(batch))
    return batch


METRIC_COLUMNS = [("garment_chamfer_x1e3", "chamfer ×1e3"), ("tracking_garment_mm", "track mm"),
                  ("psnr", "PSNR"), ("stretch_stiffness", "stretch N/m")]


def table(batch: dict, stages: list[str] | None = None) -> tuple[list[str], list[list[str]]]:
    """The summary table's header and rows: per capture its status, the seconds of ``stages``
    (default: every stage) and of all of them together, and the key metrics."""
    if stages is None:
        stages = list(dict.fromkeys(s for r in batch["captures"] for s in r["stage_seconds"]))
    head = ["capture", "status", "stages s"] + [f"{s} s" for s in stages] + [t for _, t in METRIC_COLUMNS]
    rows = []
    for r in batch["captures"]:
        m, secs = r["metrics"], r["stage_seconds"]
        rows.append([r["name"], r["status"], f"{sum(secs.values()):.1f}"]
                    + [f"{secs[s]:g}" if s in secs else "" for s in stages]
                    + [f"{m[k]:.4g}" if k in m else "" for k, _ in METRIC_COLUMNS])
    return head, rows


def batch_markdown(batch: dict) -> str:
    head, rows = table(batch)
    L = ["# physavatar batch", "",
         f"{len(batch['captures'])} captures ({batch['mode']}): {batch['ok']} ok, {batch['failed']} failed, "
         f"{batch['seconds']:.0f} s. Stage columns: seconds (of the run that made each stage's outputs). "
         f"Run settings: `{json.dumps(batch['config'])}`.", "",
         "| " + " | ".join(head) + " | report |", "|" + " --- |" * (len(head) + 1)]
    for r, row in zip(batch["captures"], rows):
        link = f"[report.md]({r['report']})" if r["report"] else ""
        L.append("| " + " | ".join(row) + f" | {link} |")
    errors = [r for r in batch["captures"] if r["status"] != "ok"]
    if errors:
        L += ["", "## Failed", ""] + [f"- **{r['name']}** (`{r['capture']}`): {r['error']}" for r in errors]
    L += ["", "Run `physavatar batch` again with the same arguments to resume: finished stages are skipped."]
    return "\n".join(L) + "\n"


def run_batch(args: list[str], out: str | Path, cfg: RunConfig = RunConfig(), *, jobs: int | None = None,
              ray: str | None = None, ray_cpus: int | None = None, say=print) -> dict:
    """Collect the captures, run them (locally, or on Ray when ``ray`` is an address or
    ``"local"``), write ``OUT/batch.json`` and ``OUT/batch.md``; returns the batch record."""
    if ray is not None:
        import_ray()  # before anything runs: a clear message when it is missing
    caps = collect(args)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.time()
    if ray is not None:
        results = run_ray(caps, out, cfg, address=ray, cpus=ray_cpus, say=say)
        mode = "Ray " + ("local" if ray in ("", "local") else ray)
    else:
        results = run_local(caps, out, cfg, jobs=jobs, say=say)
        mode = "local"
    return summarize(results, out, cfg, mode=mode, seconds=time.time() - t0)
