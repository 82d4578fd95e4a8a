"""Every motion, every frame: the dress simulated on a suite of motions, checked frame by frame.

The motions: the built-in ones, both CMU clips (``shared/data/motions/cmu_131_0{1,3}.bvh``,
arm and part clearance applied as ``simulate`` does; ``--no-part-clearance``: arm clearance
only), and synthetic stress motions (a high jump, a spin at 2 turns/s, the hands pressed to the hips (akimbo), a sit-down where the thighs fold into the lap).
And two layered cases (``simulate --over``): a t-shirt over a skirt on the walk, a dress over a
skirt (a petticoat) on the dance, simulated together with self-contact between the layers.
Each runs through ``physavatar simulate``'s stage (stages.simulate.run: the built-in dress on
Anny's collider body, cotton, sub-steps decided per frame, frames written as finished) and is
checked on every written frame: lag (the body stopped short of its pose, the step gave up),
garment-body intersection (ipctk, as ``simulate`` checks), garment self-intersection (ipctk on
the garment alone, seams left out as ``simulate`` does), NaN.

By default a quick run (a few minutes on 2 cores): a 4-cm dress, 1-s excerpts (the CMU clips'
hops and strides), a 0.4-s warm-up. ``--full``: the 2-cm dress, the clips whole, 4 s of each
built-in motion, a 1-s warm-up. ``--max-substeps 1`` runs the old fixed one step per frame.
Frames split into sub-steps pose the body in between from the motion (body.between, as
``simulate`` does by default since session 31; the attached targets on the straight line);
``--no-skinned-between``: vertex by vertex (``simulate --linear-between``).

    python benchmarks/motion_suite.py [--full] [--only NAME ...] [--max-substeps N] [--out FILE]
    python benchmarks/motion_suite.py --full --partial --only cmu-walk --work DIR   # a run not finished: its frames so far
    python benchmarks/motion_suite.py [--full] --targets   # the attached targets alone, every frame (seconds a motion)

Prints a table and writes benchmarks/results/motion_suite.json (``checks``: per motion, lag,
intersection and NaN frames must all be 0).
"""

from __future__ import annotations

import argparse
import datetime
import json
import logging
import os
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault("NUMBA_NUM_THREADS", "2")
os.environ.setdefault("OMP_NUM_THREADS", "2")
sys.path.insert(0, str(Path(__file__).resolve().parent))

import numpy as np  # noqa: E402

from _common import cpu_name  # noqa: E402
from physavatar.body import BUILTIN, BodyModel, Motion  # noqa: E402
from physavatar.body.load import describe_part_clearance, load_motion, with_clearances  # noqa: E402
from physavatar.body.motion import _x, _y, _z, bone_vertex_mask  # noqa: E402
from physavatar.data.garment_sequence import GarmentSequence  # noqa: E402
from physavatar.errors import PhysavatarError  # noqa: E402
from physavatar.files import write_json_atomic  # noqa: E402
from physavatar.sim.simulate import self_intersecting_frames  # noqa: E402
from physavatar.stages import simulate as simulate_stage  # noqa: E402

MOTIONS = Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "motions"
CLIPS = {"cmu-walk": ("cmu_131_01.bvh", 20), "cmu-hop": ("cmu_131_03.bvh", 45)}  # quick: 1 s from this frame
# layered garments (simulate --garment G --over O): name -> (garment, garments over it, motion)
LAYERED = {"layers-walk": ("skirt", "tshirt", "walk"), "layers-dance": ("skirt", "dress", "dance")}


# hands pressed to the hips, akimbo: the hand's surface this far [m] from the trunk's (session 14:
# the earlier 1-cm *vertex* distance left 0.4-1.2 mm between the surfaces, no room for the cloth)
HANDS_ON_HIPS_GAP = 0.006
AKIMBO_BONES = ("upperarm01", "lowerarm01", "lowerarm02", "wrist")


def _ramp(t, t0, t1):
    s = np.clip((t - t0) / (t1 - t0), 0.0, 1.0)
    return s * s * (3 - 2 * s)


def _frame(a, b):
    """Rotation matrix whose columns are a, b (orthogonalised against a) and a x b."""
    a = a / np.linalg.norm(a)
    b = b - (b @ a) * a
    b = b / np.linalg.norm(b)
    return np.stack([a, b, np.cross(a, b)], 1)


def _akimbo_rotations(body: BodyModel, wrist: np.ndarray, swivel: float = -0.3, hand_dir=(0.0, -1.0, 0.0),
                      palm_dir=(-1.0, 0.0, 0.0)) -> list[np.ndarray]:
    """The left arm's rotations (axis-angle, ``AKIMBO_BONES`` order) that put the wrist joint at
    ``wrist`` [m] with the elbow a hinge: the upper arm swung and rolled so that the elbow lies on
    the circle of reach, ``swivel`` [rad] behind straight out to the side; the elbow flexed to
    reach; the forearm's twist (lowerarm02) turning the palm to ``palm_dir`` (its normal) and the
    wrist bending the hand to point along ``hand_dir``."""
    from scipy.spatial.transform import Rotation

    names = body.bone_names
    r, t = body.rest_pose()
    P = body.pose(r, t)
    J, V = P.joints[0], P.vertices[0]
    S, E0, W0 = (J[names.index(b)] for b in ("upperarm01.L", "lowerarm01.L", "wrist.L"))
    L1, L2 = np.linalg.norm(E0 - S), np.linalg.norm(W0 - E0)
    u0, f0 = (E0 - S) / L1, (W0 - E0) / L2
    n0 = np.cross(u0, f0) / np.linalg.norm(np.cross(u0, f0))  # the elbow's hinge axis at rest
    # the hand at rest: wrist -> middle fingertip, and its palm normal (palm x hand = thumb side)
    hand = bone_vertex_mask(body, [n for n in names if n.startswith(("wrist", "finger", "metacarpal"))
                                   and n.endswith(".L")])
    h0 = V[bone_vertex_mask(body, ["finger3-3.L"])].mean(0) - W0
    h0 /= np.linalg.norm(h0)
    thumb = V[bone_vertex_mask(body, ["finger1-"]) & hand].mean(0) - V[hand].mean(0)
    p0 = np.cross(h0, thumb - (thumb @ h0) * h0)
    # the elbow on the circle of points L1 from the shoulder and L2 from the wrist
    d = np.asarray(wrist, float) - S
    dl = np.linalg.norm(d)
    dh = d / dl
    a = (L1**2 - L2**2 + dl**2) / (2 * dl)
    ex = np.array([1.0, 0, 0]) - dh[0] * dh
    ex /= np.linalg.norm(ex)
    E = S + a * dh + np.sqrt(max(L1**2 - a**2, 0.0)) * (np.cos(swivel) * ex + np.sin(swivel) * np.cross(dh, ex))
    u, f = (E - S) / L1, (wrist - E) / L2
    R1 = _frame(u, f) @ _frame(u0, f0).T  # upper arm: (u0, f0)'s plane onto (u, f)'s
    R2 = Rotation.from_rotvec(n0 * (np.arccos(np.clip(u @ f, -1, 1)) - np.arccos(np.clip(u0 @ f0, -1, 1))))
    R2 = R2.as_matrix()  # elbow flexion
    R3 = (R1 @ R2).T @ _frame(np.asarray(hand_dir, float), np.asarray(palm_dir, float)) @ _frame(h0, p0).T
    t0 = W0 - J[names.index("lowerarm02.L")]  # the forearm's twist axis (lowerarm02 -> wrist)
    t0 /= np.linalg.norm(t0)
    q = Rotation.from_matrix(R3).as_quat()  # hand relative to forearm = twist about t0, then swing
    tw = 2 * np.arctan2(q[:3] @ t0, q[3])
    tw = (tw + np.pi) % (2 * np.pi) - np.pi
    T = Rotation.from_rotvec(t0 * tw).as_matrix()
    return [Rotation.from_matrix(R1).as_rotvec(), Rotation.from_matrix(R2).as_rotvec(), t0 * tw,
            Rotation.from_matrix(T.T @ R3).as_rotvec()]


def _pose_arms(body: BodyModel, left: list[np.ndarray], extra: dict | None = None) -> np.ndarray:
    """[T, B, 3] rotations: ``left`` ([T, 3] or [3] per ``AKIMBO_BONES``) on the left arm, its
    mirror image (x -> -x: axis-angle (x, y, z) -> (x, -y, -z)) on the right."""
    names = body.bone_names
    left = [np.atleast_2d(r) for r in left]
    R = np.zeros((len(left[0]), len(names), 3))
    for b, r in zip(AKIMBO_BONES, left):
        R[:, names.index(f"{b}.L")] = r
        R[:, names.index(f"{b}.R")] = r * [1, -1, -1]
    for b, r in (extra or {}).items():
        R[:, names.index(b)] = r
    return R


def _trunk_and_hands(body: BodyModel):
    names = body.bone_names
    arm = bone_vertex_mask(body, [n for n in names if n.startswith(
        ("clavicle", "shoulder", "upperarm", "lowerarm", "wrist", "finger", "metacarpal"))])
    hands = bone_vertex_mask(body, [n for n in names if n.startswith(("wrist", "finger", "metacarpal"))])
    return ~arm, hands


def hand_trunk_gaps(body: BodyModel, rotations: np.ndarray, translation: np.ndarray) -> dict[str, np.ndarray]:
    """Per frame, surface distances [m] to the trunk (the body less arms, shoulders, clavicles) of
    the hands (both ways: hand vertices to trunk triangles and trunk vertices to hand triangles)
    and of the other arm bones' vertices (hands excluded): ``hand``, ``lowerarm``, ``upperarm``."""
    from physavatar.geometry import MeshQuery

    trunk, hands = _trunk_and_hands(body)
    F = np.asarray(body.faces)
    Ft, Fh = F[np.all(trunk[F], 1)], F[np.all(hands[F], 1)]
    parts = {k: bone_vertex_mask(body, [k]) & ~hands for k in ("lowerarm", "upperarm")}
    out = {k: [] for k in ("hand", *parts)}
    for V in body.pose(rotations, translation).vertices:
        q = MeshQuery(V, Ft)
        out["hand"].append(min(q.closest(V[hands], max_dist=0.1)[0].min(),
                               MeshQuery(V, Fh).closest(V[trunk], max_dist=0.1)[0].min()))
        for k, m in parts.items():
            out[k].append(q.closest(V[m], max_dist=0.3)[0].min())
    return {k: np.array(v) for k, v in out.items()}


def _hands_on_hips_pose(body: BodyModel, target: float = HANDS_ON_HIPS_GAP) -> list[np.ndarray]:
    """The left arm's akimbo rotations (``AKIMBO_BONES``; the right's are the mirror image): the
    elbow out to the side and bent, the hand pointing forward along the waist with the palm on it,
    its wrist 13 cm above the root joint and 4 cm behind it; the wrist's lateral offset found by
    bisection so that the hands' surface is ``target`` [m] from the trunk's."""
    root = body.pose(*body.rest_pose()).joints[0][body.bone_names.index("root")]

    def pose(dx):
        return _akimbo_rotations(body, root + [dx, 0.04, 0.13])

    def gap(dx):
        return hand_trunk_gaps(body, _pose_arms(body, pose(dx)), np.zeros((1, 3)))["hand"][0]

    lo, hi = 0.12, 0.20
    if not gap(lo) <= target <= gap(hi):
        raise RuntimeError("no wrist position brings the hand to the hips")
    for _ in range(12):
        mid = 0.5 * (lo + hi)
        lo, hi = (lo, mid) if gap(mid) > target else (mid, hi)
    return pose(hi)


def stress_motions(body: BodyModel, fps: float, duration: float) -> dict[str, Motion]:
    """The synthetic stress motions (Anny collider bones)."""
    names = body.bone_names
    n = int(round(duration * fps)) + 1
    t = np.arange(n) / fps
    out = {}

    def motion(name, rot_by_bone, tr):
        R = np.zeros((n, len(names), 3))
        for b, r in rot_by_bone.items():
            R[:, names.index(b)] = r
        out[name] = Motion(name, fps, names, R, tr, {"source": "motion_suite"})

    # a spin at 2 turns/s about the vertical (after a 0.25-s ease-in: 28.8° a frame at 25 fps)
    e = _ramp(t, 0, 0.25)
    ang = 2 * np.pi * 2.0 * np.cumsum(e) / fps
    motion("spin-2tps", {"root": _z(ang)}, np.zeros((n, 3)))
    # a high jump: crouch, 0.3-m ballistic flight with the knees tucked, landing (0.1 m a frame)
    crouch = np.sin(np.pi * np.clip(t / 0.3, 0, 1)) * (t < 0.3)
    flight = (t >= 0.3) & (t < 0.3 + 0.5)
    tf = np.clip(t - 0.3, 0, 0.5)
    z = np.where(flight, 2.45 * tf - 0.5 * 9.81 * tf**2, 0.0)
    tuck = np.sin(np.pi * tf / 0.5) * flight
    land = np.sin(np.pi * np.clip((t - 0.8) / 0.3, 0, 1)) * (t >= 0.8)
    bend = crouch + 0.7 * land
    tr = np.zeros((n, 3))
    tr[:, 2] = z - 0.12 * bend
    motion("jump-high", {"upperleg01.L": _x(-0.7 * bend - 0.9 * tuck), "upperleg01.R": _x(-0.7 * bend - 0.9 * tuck),
                         "lowerleg01.L": _x(1.3 * bend + 1.2 * tuck), "lowerleg01.R": _x(1.3 * bend + 1.2 * tuck),
                         "upperarm01.L": _y(-0.6 * tuck), "upperarm01.R": _y(0.6 * tuck)}, tr)
    # akimbo: the hands brought to the hips in 0.4 s and pressed there (HANDS_ON_HIPS_GAP), with a small sway
    e = _ramp(t, 0, 0.4)[:, None]
    sway = 0.05 * np.sin(2 * np.pi * 1.5 * t) * e[:, 0]
    R = _pose_arms(body, [r * e for r in _hands_on_hips_pose(body)], {"spine03": _z(sway)})
    motion("hands-on-hips", {b: R[:, i] for i, b in enumerate(names) if R[:, i].any()}, np.zeros((n, 3)))
    # sitting down in 0.8 s: the thighs fold up into the lap (hips flexed 85°, knees 90°)
    s = _ramp(t, 0.1, 0.9)
    tr = np.zeros((n, 3))
    tr[:, 2] = -0.42 * s
    tr[:, 1] = 0.12 * s
    motion("sit-down", {"upperleg01.L": _x(-1.5 * s), "upperleg01.R": _x(-1.5 * s),
                        "lowerleg01.L": _x(1.57 * s), "lowerleg01.R": _x(1.57 * s),
                        "spine03": _x(-0.15 * s)}, tr)
    return out


def garment_self_intersections(seq: GarmentSequence, prescribed: bool = False) -> list[int]:
    """Frames where the garment (all its layers) intersects itself (ipctk on the garments alone;
    the suite's garments have no sewn seams to leave out). ``prescribed``: leave out the pairs
    of the attached (boundary) vertices alone, as the solver does: their crossings come with
    the prescribed motion (the attachment riding the body's skin), not from the solve."""
    return self_intersecting_frames(np.asarray(seq.vertices, np.float64), seq.faces,
                                    prescribed=seq.boundary if prescribed else None)


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--full", action="store_true", help="2-cm dress, whole clips, 4-s built-in motions")
    ap.add_argument("--only", nargs="*", default=None, help="run only these motions (or layered cases)")
    ap.add_argument("--max-substeps", type=int, default=16, help="1: the fixed one step per frame (before)")
    ap.add_argument("--edge", type=float, default=None, help="dress edge length [m] (default 0.04, --full 0.02)")
    ap.add_argument("--out", default=None, help="result file (default benchmarks/results/motion_suite.json)")
    ap.add_argument("--no-self-contact", action="store_true", help="garment self-contact off")
    ap.add_argument("--progress", action="store_true", help="log a progress line every 5 frames")
    ap.add_argument("--reuse", action="store_true",
                    help="read the motions already simulated in --work instead of simulating them again")
    ap.add_argument("--append", action="store_true", help="keep the other motions' rows of an existing result file")
    ap.add_argument("--work", default=None, help="keep the simulate folders here (default: a temporary folder)")
    ap.add_argument("--commit", default=None,
                    help="with --partial: the code commit the runs in --work were started on (default: this checkout's)")
    ap.add_argument("--targets", action="store_true",
                    help="check only the attached (boundary) targets, simulate nothing: the frames where the "
                         "attached triangles alone cross, riding the skin and after garment.unfold_targets")
    ap.add_argument("--part-clearance", action=argparse.BooleanOptionalAction, default=True,
                    help="the CMU clips also corrected by body.clearance.part_clearance (thigh out of the belly, "
                         "calf out of the thigh, hand off the body; docs/simulation.md \"Session 23\"), as "
                         "`simulate` and `animate` do by default; --no-part-clearance: the clips as retargeted")
    ap.add_argument("--knee-collapse", nargs="?", const="on", default="auto", choices=("auto", "on", "off"),
                    help="the CMU clips also corrected by body.clearance.knee_collapse_rules (the knee opened where "
                         "calf and thigh pass through each other): auto (default, as `simulate`): only where they "
                         "cross deeper than 1 mm (d-hat; docs/simulation.md \"Session 33\"); on (or the bare flag, "
                         "session 29's opt-in): everywhere; off: nowhere")
    ap.add_argument("--skinned-between", action=argparse.BooleanOptionalAction, default=True,
                    help="a frame split into sub-steps poses the body in between from the motion (body.between, "
                         "as `simulate` does by default); --no-skinned-between: vertex by vertex (`--linear-between`)")
    ap.add_argument("--partial", action="store_true",
                    help="check the frames written so far by the (interrupted or running) runs in --work, simulate nothing")
    args = ap.parse_args()
    if args.progress:
        logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s", datefmt="%H:%M:%S")
    fps = 25.0
    edge = args.edge or (0.02 if args.full else 0.04)
    duration = 4.0 if args.full else 1.0
    warmup = 1.0 if args.full else 0.4
    body = BodyModel(topology="collider")
    work = Path(args.work) if args.work else Path(tempfile.mkdtemp(prefix="motion_suite_"))
    work.mkdir(parents=True, exist_ok=True)
    wanted = (lambda name: not args.only or name in args.only)
    specs: dict[str, str] = {name: name for name in BUILTIN if wanted(name)}
    layered = {name: v for name, v in LAYERED.items() if wanted(name)}
    for name, (clip, start) in CLIPS.items():
        path = MOTIONS / clip
        if not wanted(name):
            continue
        knee = {"auto": "-kneeauto", "on": "-knee", "off": ""}[args.knee_collapse]
        cached = work / f"{name}{'-full' if args.full else ''}{'-parts' if args.part_clearance else ''}{knee}.npz"
        if cached.exists():  # the clip retargeted with arm clearance (minutes on a loaded machine)
            specs[name] = str(cached)
            continue
        if not path.exists():
            print(f"{name}: {path} missing, skipped")
            continue
        m = load_motion(str(path), fps, 4.0, body=body)
        m, _, parts = with_clearances(m, str(path), lambda: body, 0.03, args.part_clearance,
                                      {"auto": None, "on": True, "off": False}[args.knee_collapse])  # as `simulate` does
        print(f"{name}: {describe_part_clearance(parts)}")
        write_json_atomic(cached.with_suffix(".json"), {"part_clearance": parts})
        if not args.full:
            m = m.slice(start, start + int(round(duration * fps)) + 1)
        m.save(cached)
        specs[name] = str(cached)
    for name, m in stress_motions(body, fps, max(duration, 1.2) if not args.full else 2.0).items():
        if wanted(name):
            m.save(work / f"{name}.npz")
            specs[name] = str(work / f"{name}.npz")

    rows, load0 = {}, os.getloadavg()
    print(f"dress edge {edge} m, {duration:g} s built-in motions, warm-up {warmup} s, max substeps {args.max_substeps}, "
          f"self-contact {'off' if args.no_self_contact else 'on'}")
    print(f"{'motion':15s} {'frames':>6s} {'lag':>4s} {'body-x':>6s} {'self-x':>6s} {'NaN':>4s} {'s/frame':>8s} "
          f"{'steps/frame':>11s}")
    cases = {name: ("dress", None, spec) for name, spec in specs.items()} | layered
    if args.targets:
        out = Path(args.out) if args.out else Path(__file__).resolve().parent / "results" / "motion_suite_targets.json"
        rows = {name: target_row(garment, over, spec, edge, duration, warmup, args) | _clip_clearance(spec)
                for name, (garment, over, spec) in cases.items()}
        for name, r in rows.items():
            print(f"{name:15s} {r['frames']:6d} frames: attached triangles cross in {len(r['crossing_frames_ride'])} "
                  f"riding the skin, {len(r['crossing_frames_targets'])} as simulated; changed {r['frames_unfolded']} "
                  f"frames by <= {1e3 * r['max_unfold_change_m']:.1f} mm; area {r['area_ratio_range']}")
        write_json_atomic(out, {"benchmark": "motion_suite --targets", "code_commit": _head(), "edge_length": edge,
                                "full": args.full,
                                "date": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
                                "figures": rows, "checks": {f"{k}:crossing_frames_targets": {
                                    "value": len(r["crossing_frames_targets"]), "target": "0 frames",
                                    "pass": not r["crossing_frames_targets"]} for k, r in rows.items()}})
        return
    if args.partial:
        for name, (garment, over, spec) in cases.items():
            if (work / name / "frames" / "state.npz").exists():
                rows[name] = partial_row(work / name, garment, over, spec, edge, duration, warmup, args)
                r = rows[name]
                print(f"{name:15s} {r['frames']:6d} {len(r['frames_with_lag']):4d} "
                      f"{len(r['frames_with_body_intersection']):6d} {len(r['frames_with_self_intersection']):6d} "
                      f"{len(r['frames_with_nan']):4d} {r['s_per_frame']:8.2f} {r['mean_substeps']:6.2f} "
                      f"(max {r['max_substeps']})  written frames 0-{r['frames'] - 1} of {r['frames_total']}", flush=True)
                _write(args, rows, load0, edge, duration, warmup, fps)
        return
    for name, (garment, over, spec) in cases.items():
        cfg = simulate_stage.SimulateConfig(edge_length=edge, duration=duration, warmup=warmup, preview=False,
                                            max_substeps=args.max_substeps, self_contact=not args.no_self_contact,
                                            over=over, skinned_between=args.skinned_between)
        done = work / name / "config.json"
        t0 = time.perf_counter()
        reused = args.reuse and done.exists()
        if not reused:  # (an interrupted run in work/name resumes)
            try:
                simulate_stage.run(out=work / name, config=cfg, garment=garment, motion=spec)
            except PhysavatarError as e:  # refused before its first step (e.g. layers closer than d̂): a failing row
                rows[name] = {"garment": garment if over is None else f"{garment} under {over}", "refused": str(e),
                              "frames": 0, **{k: [] for k in ("frames_with_lag", "frames_with_body_intersection",
                                                             "frames_with_self_intersection", "frames_with_nan")}}
                print(f"{name:15s} refused: {e}", flush=True)
                _write(args, rows, load0, edge, duration, warmup, fps)
                continue
        wall = time.perf_counter() - t0
        rec = json.loads(done.read_text())
        seq = GarmentSequence.load(work / name, finite=False)
        nan = [f for f in range(seq.n_frames) if not np.all(np.isfinite(seq.vertices[f]))]
        body_x = [f for f in rec["frames_with_intersection_or_nan"] if f not in nan]
        self_x = garment_self_intersections(seq)
        solver_x = garment_self_intersections(seq, prescribed=True) if self_x else []
        steps = rec["per_frame"]["substeps"]
        frames, warm = rec["frames"], rec["warmup_frames"]
        simulated = frames + warm - 1
        row = {"garment": garment if over is None else f"{garment} under {over}", "vertices": seq.vertices.shape[1],
               "frames": frames, "warmup_frames": warm, "frames_with_lag": rec["frames_with_lag"],
               "frames_with_body_intersection": body_x, "frames_with_self_intersection": self_x,
               "frames_with_nan": nan,
               # of the self-intersecting frames, those where more than the attached vertices' own
               # triangles cross (those are prescribed: sim.contact.prescribed_filter)
               "frames_with_self_intersection_beyond_prescribed": solver_x, "s_per_frame": rec["seconds"] / max(simulated, 1), "wall_s": wall,
               "reused": bool(reused),
               "resumed_after_frame": rec.get("resumed_after_frame"),
               "mean_substeps": float(np.mean(steps)) if steps else 1.0, "max_substeps": int(max(steps, default=1)),
               "newton_iterations": int(sum(rec["per_frame"]["newton_iterations"])),
               "max_lag_m": float(max(rec["per_frame"]["lag_m"], default=0.0)), **_clip_clearance(spec)}
        rows[name] = row
        print(f"{name:15s} {frames:6d} {len(row['frames_with_lag']):4d} {len(body_x):6d} {len(self_x):6d} "
              f"{len(nan):4d} {row['s_per_frame']:8.2f} {row['mean_substeps']:6.2f} (max {row['max_substeps']})",
              flush=True)
        _write(args, rows, load0, edge, duration, warmup, fps)
    failed = [k for k, c in _checks(rows).items() if not c["pass"]]
    print(f"\n{len(_checks(rows)) - len(failed)}/{len(_checks(rows))} checks pass" + (f"; failing: {failed}" if failed else ""))


def partial_row(run: Path, garment, over, spec, edge, duration, warmup, args) -> dict:
    """The row of a run not finished yet: its frames written so far (run/frames/, as
    ``simulate`` writes them) checked like a finished run's. Written frame k is simulated
    frame k + warm-up frames; frame reports, lag and checks count written frames only."""
    from physavatar.data.material import resolve_material
    from physavatar.sim import SimSettings
    from physavatar.sim.contact import ContactScene

    cfg = simulate_stage.SimulateConfig(edge_length=edge, duration=duration, warmup=warmup, preview=False,
                                        max_substeps=args.max_substeps, self_contact=not args.no_self_contact, over=over,
                                        skinned_between=args.skinned_between)
    mat = resolve_material(cfg.material, option="--material")
    part, bodies, bf, n_warm, *_ = simulate_stage._on_motion(garment, spec, 25.0, cfg, mat, SimSettings(), None)
    folder = run / "frames"
    done = sorted(int(f.stem) for f in folder.glob("[0-9]*.npz"))
    last = max(f for f in range(len(done) + 1) if done[:f] == list(range(1, f + 1)))
    reports = [json.loads(str(np.load(folder / f"{f:06d}.npz")["report"])) for f in range(1, last + 1)]
    X = np.stack([np.load(folder / f"{f:06d}.npz")["x"] for f in range(n_warm, last + 1)])
    B = bodies[n_warm:last + 1]
    scene = ContactScene(part.rest_shape, part.faces, B[0], bf, SimSettings().dhat)
    nan = [f for f in range(len(X)) if not np.all(np.isfinite(X[f]))]
    body_x = [f for f in range(len(X)) if f not in nan and scene.has_intersections(np.vstack([X[f], B[f]]))]
    seq = GarmentSequence(X, part.faces, part.boundary, B, bf, 25.0, part.rest_shape)
    self_x = garment_self_intersections(seq)
    written = [r for r in reports if r["frame"] >= n_warm]
    steps = [r["substeps"] for r in written]
    return {"garment": garment, "vertices": X.shape[1], "frames": len(X), "frames_total": len(bodies) - n_warm,
            "warmup_frames": n_warm, "partial": True,
            "frames_with_lag": [r["frame"] - n_warm for r in written if r["lagged"]],
            "frames_with_body_intersection": body_x, "frames_with_self_intersection": self_x,
            "frames_with_self_intersection_beyond_prescribed": garment_self_intersections(seq, True) if self_x else [],
            "frames_with_nan": nan, "s_per_frame": float(np.mean([r["seconds"] for r in reports])),
            "mean_substeps": float(np.mean(steps)) if steps else 1.0, "max_substeps": int(max(steps, default=1)),
            "max_lag_m": float(max((r["lag_m"] for r in written), default=0.0)),
            # body (and attached cloth) vertices short of their pose: all of them before sim.lag
            "max_lag_vertices": int(max((r.get("lag_vertices", -1) for r in written), default=0)),
            "per_frame": [{**r, "written_frame": r["frame"] - n_warm} for r in reports]}


def target_row(garment, over, spec, edge, duration, warmup, args) -> dict:
    """The attached targets of a case, as ``simulate`` makes them (garment_sim.boundary_targets),
    checked on every frame (simulated frames, warm-up included): where the attached triangles
    alone cross riding the skin, where they cross as simulated, how much unfold_targets moved
    them, the attached triangles' area range against frame 0, the frames keep_clear lifted."""
    from physavatar.data.material import resolve_material
    from physavatar.garment.unfold import crossing_frames
    from physavatar.garment_sim import boundary_targets
    from physavatar.sim import SimSettings
    from physavatar.stages.garment_file import repaired_start

    cfg = simulate_stage.SimulateConfig(edge_length=edge, duration=duration, warmup=warmup, preview=False,
                                        max_substeps=args.max_substeps, self_contact=not args.no_self_contact, over=over,
                                        skinned_between=args.skinned_between)
    mat, ss = resolve_material(cfg.material, option="--material"), SimSettings()
    part, bodies, bf, n_warm, *_ = simulate_stage._on_motion(garment, spec, 25.0, cfg, mat, ss, None)
    part, _ = repaired_start(part, bodies[0], bf, ss.dhat, cfg.repair_limit, garment)
    T, rep = boundary_targets(part, bodies, bf, ss.dhat)
    ids = part.boundary
    remap = -np.ones(len(part.vertices), np.int64)
    remap[ids] = np.arange(len(ids))
    Fb = remap[part.faces[(remap[part.faces] >= 0).all(1)]]
    area = np.linalg.norm(np.cross(T[:, Fb[:, 1]] - T[:, Fb[:, 0]], T[:, Fb[:, 2]] - T[:, Fb[:, 0]]), axis=-1)
    ratio = area / np.maximum(area[:1], 1e-30) if len(Fb) else np.ones((1, 1))
    return {"garment": garment if over is None else f"{garment} under {over}", "frames": len(T), "warmup_frames": n_warm,
            "boundary_vertices": len(ids), "attached_triangles": len(Fb),
            "crossing_frames_ride": rep["unfold"]["frames_crossing"],
            "crossing_frames_targets": crossing_frames(T, part.faces, ids),
            "frames_unfolded": rep["unfold"]["frames_changed"], "max_unfold_change_m": rep["unfold"]["max_change_m"],
            "area_ratio_range": [round(float(ratio.min()), 3), round(float(ratio.max()), 3)],
            "keep_clear": {k: v for k, v in rep["keep_clear"].items()}}


def _clip_clearance(spec) -> dict:
    """A CMU clip's part clearance summary (what each rule turned; the knee's windows opened or
    left), as written beside the cached clip; {} for other motions."""
    side = Path(str(spec)).with_suffix(".json")
    ok = str(spec).endswith(".npz") and side.exists()
    return {"clip_part_clearance": json.loads(side.read_text())["part_clearance"]} if ok else {}


def _checks(rows: dict) -> dict:
    checks = {}
    for name, row in rows.items():
        for key in ("frames_with_lag", "frames_with_body_intersection", "frames_with_self_intersection",
                    "frames_with_nan"):
            checks[f"{name}:{key}"] = {"value": len(row[key]), "target": "0 frames", "unit": "frames",
                                       "pass": not row[key]}
        if "refused" in row:
            checks[f"{name}:simulated"] = {"value": row["refused"], "target": "simulated", "pass": False}
    return checks


def _head() -> str | None:
    """This checkout's commit (None outside git)."""
    import subprocess

    r = subprocess.run(["git", "rev-parse", "--short=12", "HEAD"], cwd=Path(__file__).resolve().parent,
                       capture_output=True, text=True, check=False)
    return r.stdout.strip() or None


def _write(args, rows, load0, edge, duration, warmup, fps):
    """The result file, rewritten after every motion; with --append, rows of an earlier run in
    it are kept (each row says the run it came from: its date and load)."""
    out = Path(args.out) if args.out else Path(__file__).resolve().parent / "results" / "motion_suite.json"
    stamp = {"date": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
             "load_average_1_5_15min_start": [round(v, 2) for v in load0],
             "load_average_1_5_15min_now": [round(v, 2) for v in os.getloadavg()]}
    for row in rows.values():
        row.setdefault("run", stamp)
    old = json.loads(out.read_text())["figures"] if args.append and out.exists() else {}
    rows = {**old, **rows}
    result = {
        "benchmark": "motion_suite", "date": stamp["date"], "code_commit": args.commit or _head(),
        "partial": bool(args.partial),
        "machine": {"cores": os.cpu_count(), "cpu": cpu_name(), "gpu": None, **{k: v for k, v in stamp.items() if k != "date"}},
        "config": {"garment": "dress (layered cases: their rows' garment)", "edge_length": edge, "material": "cotton", "fps": fps, "full": args.full,
                   "duration_s": duration, "warmup_s": warmup, "max_substeps": args.max_substeps,
                   "self_contact": not args.no_self_contact, "part_clearance": args.part_clearance, "knee_collapse": args.knee_collapse,
                   "skinned_between": args.skinned_between,
                   "clip_excerpts": None if args.full else {k: [s, s + int(round(duration * fps))]
                                                            for k, (_, s) in CLIPS.items()}},
        "figures": rows,
        "checks": _checks(rows),
    }
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(result, indent=2) + "\n")


if __name__ == "__main__":
    main()
