"""A motion from a name or a file: the built-in motions (``motion``), the project's ``.npz``
motions, ``.bvh`` motion capture (``bvh``) and AMASS/SMPL ``.npz`` motions (``amass``), both
retargeted onto Anny. An ``.npz`` is told apart by its arrays (``rotations`` + ``bone_names``: the
project's; ``poses`` + ``trans``: AMASS). Sits above the readers, so none imports another's way back."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import PhysavatarError
from .amass import import_amass, is_amass
from .bvh import import_bvh
from .clearance import KNEE_ROOM, default_rules, knee_collapse_rules, part_clearance
from .model import BodyModel
from .motion import BUILTIN, Motion, arm_clearance, builtin_motion


def is_amass_file(path: str | Path) -> bool:
    """Whether ``path`` is an ``.npz`` holding an AMASS/SMPL motion (read by its array names)."""
    path = Path(path)
    if path.suffix.lower() != ".npz" or not path.is_file():
        return False
    try:
        with np.load(path, allow_pickle=False) as z:
            return is_amass(z.files)
    except Exception:
        return False  # Motion.load reports what is wrong with it


def is_capture(spec: str | Path) -> bool:
    """Motion capture retargeted onto Anny (``.bvh`` or AMASS ``.npz``), as opposed to a built-in
    motion or a motion already made for Anny."""
    return str(spec).lower().endswith(".bvh") or is_amass_file(spec)


def load_motion(spec: str, fps: float = 25.0, duration: float = 4.0, *, mapping: str | Path | None = None,
                body: BodyModel | None = None) -> Motion:
    """A motion by built-in name (``duration`` seconds), ``.npz`` file (the project's or AMASS) or
    ``.bvh`` file (capture retargeted onto ``body``, default Anny's collider topology, with
    ``mapping`` overrides of the joint map), at ``fps``."""
    if fps <= 0 or duration <= 0:
        raise PhysavatarError(None, "option --fps/--duration: must be positive")
    body = body or BodyModel(topology="collider")
    if spec in BUILTIN:
        return builtin_motion(spec, body.bone_names, fps, duration)
    path = Path(spec)
    if path.suffix.lower() == ".bvh":
        return import_bvh(path, body, mapping=mapping).resample(fps)
    if path.suffix.lower() == ".npz":
        if is_amass_file(path):
            return import_amass(path, body, mapping=mapping).resample(fps)
        return Motion.load(path).resample(fps).for_bones(body.bone_names)
    if not path.exists():
        raise PhysavatarError(path, f"not a built-in motion ({', '.join(BUILTIN)}) and no such file")
    raise PhysavatarError(path, "motion files must be .bvh or .npz")


def with_arm_clearance(motion: Motion, spec: str, body: BodyModel, clearance: float) -> tuple[Motion, dict | None]:
    """Motion capture (``.bvh``, AMASS ``.npz``) with the arms raised where the hands would pinch the garment
    against the trunk (:func:`arm_clearance`); other motions unchanged. Returns the motion and a
    per-side summary of what changed (None when nothing was done)."""
    if clearance < 0:
        raise PhysavatarError(None, "option --arm-clearance: must be >= 0")
    if clearance == 0 or not is_capture(spec):
        return motion, None
    m2, info = arm_clearance(motion, body, clearance)
    summary = {side: {"frames_raised": int(np.sum(d["angle_rad"] > 1e-3)),
                      "max_angle_deg": round(float(np.degrees(d["angle_rad"].max())), 1),
                      "min_distance_before_m": round(float(d["distance_before_m"].min()), 4),
                      "min_distance_after_m": round(float(d["distance_after_m"].min()), 4)} for side, d in info.items()}
    return m2, summary


KNEE_COLLAPSE_HELP = ("with a .bvh/AMASS motion and --part-clearance: open the knee where calf and thigh pass through "
                      "each other (at most 25 deg; body.clearance.knee_collapse_rules): the cloth caught in that fold "
                      "has no place outside the body. Default auto: only windows of frames where they cross deeper than "
                      "the cloth's contact needs (d-hat + contact offset; 1 mm for cotton), decided from the motion "
                      "before simulating; --knee-collapse: every collapse (before session 33: clears the CMU hop, costs "
                      "the CMU walk 16 frames); --no-knee-collapse: none (docs/simulation.md, Sessions 29 and 33)")
# simulate's and animate's --knee-collapse (None: auto)


def with_part_clearance(motion: Motion, spec: str, body: BodyModel, on: bool,
                        knee_collapse: bool | None = None, room: float = KNEE_ROOM) -> tuple[Motion, dict | None]:
    """Motion capture with the parts a garment covers kept apart (:func:`body.clearance.part_clearance`:
    thigh out of the belly, calf out of the thigh, hands off the body) when ``on``, and then the
    knee opened where calf and thigh pass through each other (:func:`body.clearance.knee_collapse_rules`,
    ``--knee-collapse``): ``knee_collapse`` True: every collapse; None (auto, with ``on`` only):
    windows of frames crossing at least ``room`` [m] deep (the cloth's d̂ + contact offset); False:
    none. Other motions and all off unchanged. Returns the motion and, per rule that turned a bone,
    the frames turned, the largest turn [deg] and the closest distance (a collapse rule: minus the
    deepest buried vertex) before and after [m]; an auto collapse rule that found a collapse also
    its windows (frames, deepest crossing, opening, opened or left) (None when nothing was done)."""
    knee = knee_collapse is True or (knee_collapse is None and on)
    if not (on or knee) or not is_capture(spec):
        return motion, None
    m2, info = part_clearance(motion, body, default_rules()) if on else (motion, {})
    if knee:
        m2, more = part_clearance(m2, body, knee_collapse_rules(room if knee_collapse is None else 0.0))
        info = info | more
    summary = {}
    for name, d in info.items():
        turned = d["angle_rad"] > 1e-3
        if turned.any() or d.get("windows"):
            closest = {f"min_distance_{k}_m": round(float(d[f"distance_{k}_m"][turned].min()), 4) if turned.any() else None
                       for k in ("before", "after")}
            summary[name] = {"frames_turned": int(turned.sum()),
                             "max_angle_deg": round(float(np.degrees(d["angle_rad"].max())), 1), **closest}
        if d.get("windows"):
            summary[name]["min_depth_m"] = room
            summary[name]["windows"] = [{"frames": [int(w["frames"][0]), int(w["frames"][-1])],
                                         "deepest_m": round(float(w["depth_m"].max()), 5),
                                         "opening_deg": round(float(np.degrees(w["opening_rad"].max())), 3),
                                         "opened": w["opened"]} for w in d["windows"]]
    return m2, summary or None


def with_clearances(motion: Motion, spec: str, make_body, arm: float, parts: bool,
                    knee_collapse: bool | None = None, room: float = KNEE_ROOM) -> tuple[Motion, dict | None, dict | None]:
    """Motion capture with the corrections of ``simulate`` and ``animate`` applied: arm clearance
    (``arm`` [m], :func:`with_arm_clearance`) and then part clearance (``parts``, ``knee_collapse``,
    ``room``: :func:`with_part_clearance`). ``make_body()`` gives the collider they measure on; it is built
    only when a correction applies. Returns the motion and the two summaries."""
    if arm < 0:
        raise PhysavatarError(None, "option --arm-clearance: must be >= 0")
    if not (arm or parts or knee_collapse) or not is_capture(spec):
        return motion, None, None
    body = make_body()
    motion, arm_info = with_arm_clearance(motion, spec, body, arm)
    motion, parts_info = with_part_clearance(motion, spec, body, parts, knee_collapse, room)
    return motion, arm_info, parts_info


def describe_clearance(summary: dict | None, clearance: float) -> str | None:
    """One line saying which arms were raised and by how much (None when none was)."""
    raised = {k: v for k, v in (summary or {}).items() if v["frames_raised"]}
    if not raised:
        return None
    return "arm clearance: " + "; ".join(
        f"{side} arm raised in {v['frames_raised']} frames (up to {v['max_angle_deg']} deg), hand-to-trunk "
        f"{1000 * v['min_distance_before_m']:.0f} -> {1000 * v['min_distance_after_m']:.0f} mm"
        for side, v in raised.items()) + f" (--arm-clearance {clearance:g} m; 0 keeps the motion as it is)"


def describe_part_clearance(summary: dict | None) -> str | None:
    """One line saying which bones --part-clearance turned and by how much (None when none was)."""
    if not summary:
        return None

    def one(name, v):
        said = (f"{name} in {v['frames_turned']} frames (up to {v['max_angle_deg']} deg), closest "
                f"{1000 * v['min_distance_before_m']:.0f} -> {1000 * v['min_distance_after_m']:.0f} mm"
                if v["frames_turned"] else f"{name} turned nowhere")
        left = [w for w in v.get("windows", ()) if not w["opened"]]
        if left:
            said += (", left where calf and thigh cross by less than " f"{1000 * v['min_depth_m']:.1f} mm: frames "
                     + ", ".join(f"{w['frames'][0]}-{w['frames'][1]} ({1000 * w['deepest_m']:.2f} mm)" for w in left))
        return said
    return "part clearance: " + "; ".join(one(name, v) for name, v in summary.items())


def inspect_capture(spec: str | Path, body: BodyModel, mapping: str | Path | None = None) -> dict:
    """What ``motion inspect`` shows of a ``.bvh`` or AMASS ``.npz``: the skeleton (names,
    parents, channels per joint), frames, fps, what it is, and the motion retargeted onto ``body``
    at the file's fps (its ``meta`` holds the joint map, the reasons, axes and scale)."""
    from .amass import SMPL_NAMES, SMPL_PARENTS, read_amass
    from .bvh import read_bvh

    path = Path(spec)
    if path.suffix.lower() == ".bvh":
        b = read_bvh(path)
        sk = b.skeleton
        return {"kind": "BVH", "names": list(sk.names), "parents": np.asarray(sk.parents),
                "channels": [len(c) for c in sk.channels], "frames": len(b.data), "fps": b.fps,
                "motion": import_bvh(path, body, mapping=mapping)}
    if is_amass_file(path):
        d = read_amass(path)
        return {"kind": f"AMASS / {d['model']}", "names": list(SMPL_NAMES), "parents": SMPL_PARENTS,
                "channels": None, "frames": len(d["poses"]), "fps": d["fps"],
                "motion": import_amass(path, body, mapping=mapping)}
    if not path.exists():
        raise PhysavatarError(path, "no such file")
    raise PhysavatarError(path, "not motion capture: expected a .bvh file or an AMASS/SMPL .npz (poses, trans, mocap_framerate)")
