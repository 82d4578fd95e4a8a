"""Simulated frames per second of physavatar.sim: the demo dress on the demo walk, self-contact on,
against the code of an earlier commit run side by side.

The garment and body are those of the synthetic "demo" capture (synth.PRESETS["demo"]): the
2-cm dress (~3,350 vertices) on Anny's collider-topology body, the built-in "walk" at 25 fps,
one implicit step per frame (dt = 0.04 s), the cotton preset, garment self-contact on (the
default of `simulate`/`animate`), simulated through the project's own path
(garment_sim.simulate_on_body: boundary vertices attached to the body surface).

Two worker processes simulate the same scene: this tree's code ("new") and the ``--baseline``
commit's (its ``src/`` exported with ``git archive`` into a cache folder, run with PYTHONPATH
pointing there; default: main at the start of session 23). They run in lockstep, one
frame each in turn, so that both see the same load on a shared machine, and the speed ratio
new / baseline is taken from the same run. Each worker first simulates 3 frames untimed (numba's
compilation, imports), then the timed walk; afterwards (untimed) it checks every frame with
ipctk (cloth–body and cloth–cloth intersections, NaN) and times one sparse Cholesky
factorisation of the full free-DOF Newton matrix at its last state (the floor of an implicit
step, measured in the same process, so "step / factorisation" survives a loaded machine).

``--large``: a finer dress (``--large-edge``, default 9.3 mm: > 15k vertices) on Anny's full-
resolution body (> 12k vertices), a few frames of the walk, new code only (the baseline took
> 3 min a frame on this size; ``--large-baseline`` runs it too), no untimed warm-up (the
first frame includes the simulator's setup): frames/s and peak memory (the worker's VmHWM).

Writes benchmarks/results/sim_speed.json (DESIGN.md "Benchmarks"): per code, frames/s, Newton
iterations, factorisations and CG iterations per frame, the split of a frame's time, step /
factorisation; the ratio; ``checks`` (fps ≥ 2 and step ≤ 4 factorisations for the new code,
no intersection or NaN, pass or fail as measured).

    python benchmarks/sim_speed.py [--quick] [--frames N] [--baseline REF | --no-baseline]
        [--large [--large-frames N] [--large-edge M]] [--set FIELD=VALUE] [--out FILE]
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault("NUMBA_NUM_THREADS", "2")
os.environ.setdefault("OMP_NUM_THREADS", "2")
HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
sys.path.insert(0, str(HERE))

import numpy as np  # noqa: E402

BASELINE = "ce87dd4"  # main at the start of session 23
FPS_TARGET = 2.0
FACT_TARGET = 4.0
WARMUP_FRAMES = 3


# -- the scene (built once, in the parent) ---------------------------------------------------

def build_scene(frames: int, edge_length: float | None = None, topology: str | None = None):
    """(arrays of the GarmentPart, bodies [T, Nb, 3], body faces, fps, material name)."""
    from dataclasses import replace

    from physavatar.body import builtin_motion
    from physavatar.garment_sim import split_template
    from physavatar.synth import PRESETS, build_template

    cfg = PRESETS["demo"]
    if edge_length is not None:
        cfg = replace(cfg, edge_length=edge_length)
    if topology is not None:
        cfg = replace(cfg, body_topology=topology)
    body, template, _ = build_template(cfg)
    motion = builtin_motion(cfg.motion, body.bone_names, cfg.fps, (frames - 1) / cfg.fps)
    posed = motion.pose(body)
    _, body_faces, part = split_template(template.vertices, template.faces, template.labels, template.boundary)
    arrays = {"vertex_ids": part.vertex_ids, "vertices": part.vertices, "faces": part.faces,
              "boundary": part.boundary, "bodies": np.asarray(posed.vertices, np.float64),
              "body_faces": np.asarray(body_faces)}
    if part.rest is not None:
        arrays["rest"] = part.rest
    if part.seams is not None:
        arrays["seams"] = part.seams
    return arrays, float(cfg.fps), cfg.material


# -- the worker (one code version) -----------------------------------------------------------

def _emit(kind, payload=None):
    print("@@" + json.dumps({"kind": kind, "payload": payload}), flush=True)


def peak_rss_mb(resource) -> float:
    """The worker's own peak resident memory [MB]: /proc's VmHWM (reset at exec), not
    ru_maxrss, which on Linux also counts the parent's memory at the fork (the parent holds the
    Anny model that built the scene: ~3.2 GB on the large case)."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return float(line.split()[1]) / 1024.0
    except OSError:
        pass
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def worker(scene_file: str, spec: dict):
    """Simulate the scene with whatever ``physavatar`` is on the path, in lockstep with the
    parent: after each frame, report and wait for a line on stdin."""
    import resource

    from physavatar.garment import attachment_positions, make_attachment
    from physavatar.garment_sim import GarmentPart, simulate_on_body
    from physavatar.sim import ClothSim, SimSettings, preset
    from physavatar.sim.assembly import Factorization
    from physavatar.sim.contact import ContactScene

    z = np.load(scene_file)
    part = GarmentPart(z["vertex_ids"], z["vertices"], z["faces"], z["boundary"],
                       z["rest"] if "rest" in z else None, z["seams"] if "seams" in z else None)
    bodies, body_faces = z["bodies"], z["body_faces"]
    frames = spec["frames"]
    bodies = bodies[:frames]
    material = preset(spec["material"])
    fields = SimSettings.__dataclass_fields__
    settings = SimSettings(dt=1.0 / spec["fps"], **{k: v for k, v in spec["settings"].items() if k in fields})
    if spec.get("warmup", WARMUP_FRAMES) > 1:
        simulate_on_body(part, bodies[: spec.get("warmup", WARMUP_FRAMES)], body_faces, material, spec["fps"],
                         settings=settings)
    _emit("ready")
    sys.stdin.readline()
    stats = []
    t_go = [time.perf_counter(), time.process_time()]

    def callback(f, x, st):
        seconds = time.perf_counter() - t_go[0]
        cpu = time.process_time() - t_go[1]  # all of the worker's threads
        stats.extend(st)
        s = st[0]
        _emit("frame", {"frame": f, "seconds": seconds, "cpu_seconds": cpu, "newton": sum(x.newton_iterations for x in st),
                        "penalty": sum(x.penalty_iterations for x in st),
                        "factorizations": sum(x.factorizations for x in st),
                        "cg": sum(x.cg_iterations for x in st), "contacts": s.n_contacts,
                        "converged": all(x.converged for x in st),
                        "time": {k: sum(x.time[k] for x in st) for k in s.time}})
        sys.stdin.readline()
        t_go[:] = [time.perf_counter(), time.process_time()]

    t0 = time.perf_counter()
    traj = simulate_on_body(part, bodies, body_faces, material, spec["fps"], settings=settings, callback=callback)
    wall = time.perf_counter() - t0
    peak_mb = peak_rss_mb(resource)
    # every frame intersection-free (cloth–body and, with self-contact, cloth–cloth) and finite
    scene = ContactScene(part.vertices, part.faces, bodies[0], body_faces, settings.dhat,
                         self_contact=settings.self_contact)
    bad = [f for f in range(len(traj))
           if not np.all(np.isfinite(traj[f])) or scene.has_intersections(np.vstack([traj[f], bodies[f]]))]
    # one sparse Cholesky of the full free-DOF Newton matrix at the last state (and of the
    # sparsified matrix the CG preconditioner factorises)
    sim = ClothSim(part.rest_shape, part.faces, material, settings, part.boundary, extra_terms=part.terms())
    att = make_attachment(part.vertices[part.boundary], part.boundary, bodies[0], body_faces, "sequence")
    tgt = attachment_positions(att, bodies[-1:])[0][np.argsort(part.boundary, kind="stable")]
    x_last = traj[-1]
    sim.step(x_last, np.zeros_like(x_last), bodies[-1], bodies[-1], body_faces, tgt)
    X = np.vstack([x_last, bodies[-1]])
    sim.scene.prepare_static(X)
    H = sim.assembler_free.assemble([t.hessian(X, project=True) for t in sim.active_terms()])
    P = sim.assembler_free.preconditioner_matrix(H)
    fact = []

    def factorise(M, backend):  # cholespy: the unit of "step / factorisation" since session 3
        try:
            return Factorization(M, backend)
        except TypeError:  # code before session 21: cholespy only
            return Factorization(M)

    for M in (H, P):
        factorise(M, "cholespy")
        t1 = time.perf_counter()
        for _ in range(3):
            factorise(M, "cholespy")
        fact.append((time.perf_counter() - t1) / 3)
    t1 = time.perf_counter()
    backend = factorise(P, settings.linear_solver if hasattr(settings, "linear_solver") else "cholespy")
    fact.append(time.perf_counter() - t1)  # the preconditioner's factorisation on the code's own backend
    _emit("done", {"wall": wall, "peak_rss_mb": peak_mb, "bad_frames": bad, "factorization_s": fact[0],
                   "preconditioner_factorization_s": fact[1], "own_backend": getattr(backend, "backend", "cholespy"),
                   "own_preconditioner_factorization_s": fact[2], "dofs": int(H.shape[0]), "nnz": int(H.nnz),
                   "garment_vertices": len(part.vertices), "body_vertices": int(bodies.shape[1]),
                   "min_distance_m": float(min(s.min_distance for s in stats)),
                   "load_end": os.getloadavg()})


# -- the parent ------------------------------------------------------------------------------

def baseline_src(ref: str) -> Path:
    """``src/`` of commit ``ref``, exported once into a cache folder (its numba cache stays)."""
    sha = subprocess.run(["git", "rev-parse", "--short=12", ref], cwd=ROOT, check=True, capture_output=True,
                         text=True).stdout.strip()
    dest = Path(os.environ.get("XDG_CACHE_HOME", Path.home() / ".cache")) / "physavatar" / "sim_speed" / sha
    if not (dest / "src" / "physavatar").is_dir():
        dest.mkdir(parents=True, exist_ok=True)
        archive = subprocess.run(["git", "archive", sha, "src"], cwd=ROOT, check=True, capture_output=True).stdout
        subprocess.run(["tar", "-x", "-C", str(dest)], input=archive, check=True)
    return dest / "src"


class Worker:
    def __init__(self, name, src: Path, scene_file, spec):
        env = dict(os.environ, PYTHONPATH=str(src), PYTHONUNBUFFERED="1")
        self.name = name
        self.proc = subprocess.Popen([sys.executable, __file__, "--worker", scene_file, json.dumps(spec)],
                                     env=env, stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
        self.frames = []
        self.done = None

    def read(self):
        for line in self.proc.stdout:
            if line.startswith("@@"):
                msg = json.loads(line[2:])
                return msg["kind"], msg["payload"]
        raise RuntimeError(f"{self.name} worker ended early (exit {self.proc.wait()})")

    def go(self):
        self.proc.stdin.write("go\n")
        self.proc.stdin.flush()


def run_lockstep(workers: list[Worker], steps: int, label: str):
    for w in workers:
        kind, _ = w.read()
        assert kind == "ready", kind
    for _ in range(steps):
        for w in workers:
            w.go()
            kind, fr = w.read()
            assert kind == "frame", kind
            w.frames.append(fr)
            print(f"{label} {w.name:8s} frame {fr['frame']:3d}: {fr['newton']:3d} Newton its ({fr['penalty']:2d} "
                  f"penalty), {fr['factorizations']} fact, {fr['cg']:4d} CG its, {fr['contacts']:4d} contacts, "
                  f"{fr['seconds']:.2f} s", flush=True)
    for w in workers:
        w.go()
        kind, w.done = w.read()
        assert kind == "done", kind
        w.proc.wait()


def figures(w: Worker) -> dict:
    fr, d = w.frames, w.done
    seconds = sum(f["seconds"] for f in fr)
    split = {k: float(np.mean([f["time"][k] for f in fr])) for k in fr[0]["time"]}
    its = [f["newton"] for f in fr]
    step = seconds / len(fr)
    return {
        "fps": len(fr) / seconds, "seconds_per_frame": step,
        # CPU seconds of the worker process (all its threads) a frame: less sensitive to the load
        "cpu_seconds_per_frame": float(np.mean([f.get("cpu_seconds", np.nan) for f in fr])),
        "newton_iterations_per_frame": float(np.mean(its)), "max_newton_iterations": int(max(its)),
        "penalty_iterations_per_frame": float(np.mean([f["penalty"] for f in fr])),
        "converged_frames": int(sum(f["converged"] for f in fr)),
        "factorizations_per_frame": float(np.mean([f["factorizations"] for f in fr])),
        "cg_iterations_per_frame": float(np.mean([f["cg"] for f in fr])),
        "time_split_s_per_frame": split,
        "factorization_s": d["factorization_s"], "preconditioner_factorization_s": d["preconditioner_factorization_s"],
        "factorization_backend": d.get("own_backend"),
        "own_backend_preconditioner_factorization_s": d.get("own_preconditioner_factorization_s"),
        "newton_matrix": {"dofs": d["dofs"], "nnz": d["nnz"]},
        "step_over_factorization": step / d["factorization_s"],
        "mean_contacts": float(np.mean([f["contacts"] for f in fr])),
        "min_distance_m": d["min_distance_m"], "frames_with_intersection_or_nan": d["bad_frames"],
        "peak_rss_mb": d["peak_rss_mb"], "newton_iterations_per_frame_series": its,
        "seconds_per_frame_series": [round(f["seconds"], 3) for f in fr],
    }


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="12 frames instead of 48")
    ap.add_argument("--frames", type=int, default=None, help="frames of the walk (incl. frame 0)")
    ap.add_argument("--baseline", default=BASELINE, help=f"git ref of the baseline code (default {BASELINE})")
    ap.add_argument("--no-baseline", action="store_true", help="run this tree's code only")
    ap.add_argument("--no-demo", action="store_true", help="skip the demo case (with --large)")
    ap.add_argument("--large", action="store_true", help="also the >= 15k-vertex garment on the full body")
    ap.add_argument("--large-frames", type=int, default=4)
    ap.add_argument("--large-edge", type=float, default=0.0093)
    ap.add_argument("--large-baseline", action="store_true", help="run the baseline on the large case too")
    ap.add_argument("--set", action="append", default=[], metavar="FIELD=VALUE",
                    help="override a SimSettings field of the new code (e.g. newton_forcing=1e-2); repeatable")
    ap.add_argument("--set-baseline", action="append", default=[], metavar="FIELD=VALUE",
                    help="override a SimSettings field of the baseline code (one it has); repeatable")
    ap.add_argument("--out", default=None, help="result file (default benchmarks/results/sim_speed.json)")
    ap.add_argument("--worker", nargs=2, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.worker:
        return worker(args.worker[0], json.loads(args.worker[1]))

    from _common import cpu_name

    frames = args.frames or (12 if args.quick else 48)
    base = {"self_contact": True}

    def parse(items):
        overrides = {}
        for item in items:
            key, _, value = item.partition("=")
            if not value:
                sys.exit(f"--set {item!r}: expected FIELD=VALUE")
            try:
                overrides[key] = json.loads(value.lower() if value.lower() in ("true", "false") else value)
            except json.JSONDecodeError:
                overrides[key] = value
        return overrides

    new_settings = base | parse(args.set)
    base = base | parse(args.set_baseline)
    codes_new = [("new", ROOT / "src")]
    codes = codes_new if args.no_baseline else [("baseline", baseline_src(args.baseline))] + codes_new
    load0 = os.getloadavg()
    result = {"benchmark": "sim_speed",
              "date": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
              "machine": {"cores": os.cpu_count(), "cpu": cpu_name(), "gpu": None,
                          "load_average_1_5_15min_start": [round(v, 2) for v in load0]},
              "config": {"baseline": None if args.no_baseline else args.baseline, "lockstep": True,
                         "warmup_frames_untimed": WARMUP_FRAMES, "settings_new": new_settings,
                         "settings_baseline": base},
              "cases": {}, "checks": {}}
    with tempfile.TemporaryDirectory(prefix="sim_speed-") as tmp:
        if not args.no_demo:
            t0 = time.perf_counter()
            arrays, fps, material = build_scene(frames)
            print(f"demo dress: {len(arrays['vertices'])} vertices, {len(arrays['faces'])} faces, "
                  f"{len(arrays['boundary'])} attached; body {arrays['bodies'].shape[1]} vertices; {frames} frames "
                  f"of 'walk' at {fps:g} fps, self-contact on (build {time.perf_counter() - t0:.1f} s)", flush=True)
            workers_specs = [(c, s, new_settings if c == "new" else base) for c, s in codes]
            scene_file = str(Path(tmp) / "demo.npz")
            np.savez(scene_file, **arrays)
            workers = [Worker(c, s, scene_file, {"frames": frames, "fps": fps, "material": material, "settings": st})
                       for c, s, st in workers_specs]
            run_lockstep(workers, frames - 1, "demo")
            figs = {w.name: figures(w) for w in workers}
            case = {"case": "synth demo: dress (edge 2 cm) on Anny 'collider' body, built-in 'walk', self-contact on",
                    "frames": frames, "steps": frames - 1, "fps": fps, "dt": 1.0 / fps, "material": material,
                    "garment_vertices": len(arrays["vertices"]), "garment_faces": len(arrays["faces"]),
                    "body_vertices": int(arrays["bodies"].shape[1]), "figures": figs}
            # the workers time their factorisations one after the other, at different loads: the
            # smallest of those times (the same cholespy call on same-sized matrices) is a common unit
            common = min(f["factorization_s"] for f in figs.values())
            for f in figs.values():
                f["step_over_common_factorization"] = f["seconds_per_frame"] / common
            case["common_factorization_s"] = common
            new = figs["new"]
            if "baseline" in figs:
                b = figs["baseline"]
                case["speed_ratio_new_over_baseline"] = new["fps"] / b["fps"]
                case["newton_iterations_ratio"] = new["newton_iterations_per_frame"] / b["newton_iterations_per_frame"]
            result["cases"]["demo"] = case
            result["checks"]["fps"] = {"value": new["fps"], "target": f">= {FPS_TARGET}", "unit": "frames/s",
                                       "pass": bool(new["fps"] >= FPS_TARGET)}
            result["checks"]["step_factorizations"] = {
                "value": new["step_over_common_factorization"], "target": f"<= {FACT_TARGET}",
                "unit": "sparse factorisations of the full Newton matrix",
                "pass": bool(new["step_over_common_factorization"] <= FACT_TARGET)}
            bad = sum(len(f["frames_with_intersection_or_nan"]) for f in figs.values())
            result["checks"]["no_intersection_or_nan"] = {"value": bad, "target": "0 frames", "unit": "frames",
                                                          "pass": bad == 0}
        if args.large:
            t0 = time.perf_counter()
            arrays, fps, material = build_scene(args.large_frames, args.large_edge, "full")
            nv, nb = len(arrays["vertices"]), arrays["bodies"].shape[1]
            print(f"large: {nv} garment vertices on a {nb}-vertex body, {args.large_frames} frames "
                  f"(build {time.perf_counter() - t0:.1f} s)", flush=True)
            codes_large = codes if args.large_baseline else codes_new
            scene_file = str(Path(tmp) / "large.npz")
            np.savez(scene_file, **arrays)
            workers = [Worker(c, s, scene_file, {"frames": args.large_frames, "fps": fps, "material": material,
                                                 "settings": new_settings if c == "new" else base, "warmup": 0})
                       for c, s in codes_large]
            run_lockstep(workers, args.large_frames - 1, "large")
            figs = {w.name: figures(w) for w in workers}
            result["cases"]["large"] = {
                "case": f"synth dress (edge {args.large_edge * 100:g} cm) on Anny 'full' body, 'walk', self-contact on",
                "frames": args.large_frames, "garment_vertices": nv, "garment_faces": len(arrays["faces"]),
                "body_vertices": int(nb), "figures": figs}
            result["checks"]["large_reported"] = {
                "value": figs["new"]["fps"], "target": ">= 0.3 (aim)", "unit": "frames/s",
                "pass": bool(figs["new"]["fps"] >= 0.3), "peak_rss_mb": figs["new"]["peak_rss_mb"],
                "sizes_ok": bool(nv >= 15000 and nb >= 12000)}
    load1 = os.getloadavg()
    result["machine"]["load_average_1_5_15min_end"] = [round(v, 2) for v in load1]
    for name, case in result["cases"].items():
        for code, f in case["figures"].items():
            print(f"\n{name} / {code}: fps {f['fps']:.3f}, {f['seconds_per_frame']:.2f} s a frame "
                  f"({f['cpu_seconds_per_frame']:.2f} CPU-s); Newton its/frame "
                  f"{f['newton_iterations_per_frame']:.1f}; factorizations {f['factorizations_per_frame']:.1f}, CG its "
                  f"{f['cg_iterations_per_frame']:.0f} a frame; step / factorisation {f['step_over_factorization']:.1f}; "
                  f"peak RSS {f['peak_rss_mb']:.0f} MB; bad frames {f['frames_with_intersection_or_nan']}")
            print("   split [s/frame]: " + ", ".join(f"{k} {v:.3f}" for k, v in f["time_split_s_per_frame"].items()))
        if "speed_ratio_new_over_baseline" in case:
            print(f"{name}: speed ratio new / baseline {case['speed_ratio_new_over_baseline']:.2f}")
    print(f"load average {load0[0]:.2f} -> {load1[0]:.2f}; checks: "
          + ", ".join(f"{k} {'pass' if v['pass'] else 'FAIL'}" for k, v in result["checks"].items()))
    out = Path(args.out) if args.out else HERE / "results" / "sim_speed.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(result, indent=2) + "\n")


if __name__ == "__main__":
    main()
