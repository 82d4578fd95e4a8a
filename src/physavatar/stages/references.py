"""The reference rows of the evaluation (paper Table 2): the true material and the random draws,
simulated on the held-out motion ahead of time (``physavatar reference-sims``, which ``run`` runs
beside tracking) and reused by :func:`physavatar.stages.evaluate.evaluate` when they were made from
what it evaluates (its avatar's start, the held-out motion, the materials in the fit's model).

Split out of stages/evaluate.py in session 34, when :func:`reference_sequences` learnt to write
each row as soon as it is simulated and to resume (docs/evaluation.md "Session 34").
"""

from __future__ import annotations

import dataclasses
import logging
import time
from pathlib import Path
from typing import NamedTuple

import numpy as np

from ..body import Motion
from ..capture import load_capture
from ..data.animated import META as SEQUENCE_META, NPZ as SEQUENCE_NPZ, AnimatedSequence
from ..data.avatar import Avatar
from ..errors import PhysavatarError
from ..files import content_key, load_npz, read_json, write_json_atomic
from ..sim import Material
from ..sim.material import FIT_REST_FRICTION, FIT_REST_SHAPE

log = logging.getLogger(__name__)

RANDOM_DRAWS = 5  # random materials per evaluation (seeds seed .. seed + 4): the row is their median


def random_material(seed: int = 0) -> Material:
    """The 'random parameters' reference of Table 2: a seeded log-uniform draw of the Codim-IPC
    setup's density (200–640 kg/m³ × thickness) and of its membrane and bending multipliers
    (0.1–10 each; docs/simulation.md gives the mapping to our units)."""
    rng = np.random.default_rng(seed)
    u = lambda lo, hi: float(np.exp(rng.uniform(np.log(lo), np.log(hi))))
    m = Material.from_codim_ipc(density_kg_m3=u(200.0, 640.0), stretch_mult=u(0.1, 10.0), bend_mult=u(0.1, 10.0))
    return dataclasses.replace(m, name=f"random-{seed}")


def random_draw_row(seed: int) -> str:
    """The name of one random draw among the reference rows (its sequence, its folder)."""
    return f"random material (seed {seed})"


def random_seeds(seed: int = 0, draws: int = RANDOM_DRAWS) -> list[int]:
    """The seeds of the random-material draws: ``seed`` … ``seed + draws - 1``."""
    return [seed + k for k in range(draws)]


class Reference(NamedTuple):
    """One reference row: its name in the metrics (``row``), its folder in a
    :func:`reference_sequences` output (``folder``) and its material."""

    row: str
    folder: str
    material: Material


def _reference_materials(gt_root: Path, seed: int, draws: int = RANDOM_DRAWS,
                         contact_offset: float = 0.0, rest_shape: str = "template",
                         rest_friction: bool = False) -> list[Reference]:
    """The rows that need only the capture: the true material (when the capture has one, folder
    ``true``; with the thickness its file records) and each random draw (:func:`random_draw_row`,
    folder ``random-<seed>``) in the simulation model of the estimate it is compared with: its
    contact thickness ``contact_offset`` [m] and its ``rest_shape`` and ``rest_friction``
    (Material.contact_offset, Material.rest_shape, Material.rest_friction: the fit's model,
    docs/physics.md)."""
    true_path = gt_root / "material.json"
    return ([Reference("true material", "true", Material.load(true_path))] if true_path.exists() else []) + \
        [Reference(random_draw_row(s), f"random-{s}", dataclasses.replace(random_material(s), contact_offset=contact_offset,
                                                                          rest_shape=rest_shape,
                                                                          rest_friction=rest_friction))
         for s in random_seeds(seed, draws)]


def reference_sequences(capture: str | Path, out: str | Path, *, frames: int | None = None, seed: int = 0,
                        random_draws: int = RANDOM_DRAWS, contact_offset: float | None = None,
                        rest_shape: str = FIT_REST_SHAPE, rest_friction: bool = FIT_REST_FRICTION,
                        progress=True) -> Path:
    """The true- and random-material rows of :func:`evaluate` simulated ahead of time.

    They depend on the capture alone (its template, body shape and frame-1 pose; the held-out
    motion; the ground-truth material; the seed), not on anything fitted, so ``physavatar run``
    computes them on the second core while tracking runs on the first. Writes
    ``out/avatar`` (a bare avatar of the capture), ``out/true`` and ``out/random-<seed>`` for each
    random draw (``animate`` folders, without PLYs) and ``out/references.json``.

    The random draws are simulated with the contact thickness the fit will use
    (``contact_offset``, ``--contact-offset``; None: estimated on the template as fit-physics
    estimates it, physics.stage.template_contact_offset) and the rest shape the fit's material
    will record (``rest_shape`` and ``rest_friction``, Material.rest_shape and
    Material.rest_friction: `run` passes its fit's); references.json records them, each draw's sequence.json the model it was simulated in (animate.simulated_material),
    and :func:`evaluate` does not reuse draws made in another model than the avatar's.

    Resumes (session 34): each row is written as soon as its simulation ends (in its own process,
    into a temporary folder renamed into place), with the key of what it was made from (its
    requested material, the avatar's start and the motion: :func:`_row_key`); a rerun on the same
    ``out`` reuses every row whose key is today's and simulates only the others, so a stopped run
    loses at most the rows still simulating. references.json, written when every row is there,
    lists the rows reused (``reused``).
    """
    from .physics.stage import template_contact_offset
    from .avatar import build_avatar
    from ..parallel import Job, run_jobs
    from .animate import simulated_frames

    cap = load_capture(capture)
    gt_root = cap.ground_truth
    if gt_root is None or not (gt_root / "heldout" / "motion.npz").exists():
        raise PhysavatarError(cap.root, "has no ground_truth/heldout (evaluation needs a synthetic capture)")
    out = Path(out)
    held = Motion.load(gt_root / "heldout" / "motion.npz")
    if frames:
        held = held.slice(0, frames)
    offset, offset_info = template_contact_offset(cap.template, contact_offset)
    rest_friction = rest_friction and rest_shape == "equilibrium"  # (a template rest solves nothing)
    refs = _reference_materials(gt_root, seed, random_draws, offset, rest_shape, rest_friction)
    av = build_avatar(cap, out / "avatar", material=refs[0].material)
    n_sim = simulated_frames(av, held)
    t0 = time.time()
    keys = {r.row: _row_key(av, r.material, held) for r in refs}
    done = [r.row for r in refs if _row_done(out / r.folder, keys[r.row], len(av.template.vertices))]
    todo = [r for r in refs if r.row not in done]
    if done:
        log.info("reference-sims: %s already in %s (reused)", ", ".join(done), out)
    meta = {"command": "reference-sims", "motion": held.name, "seed": seed}
    jobs = [Job(r.row, reference_row_job, (av.root, r.material, held, str(out / r.folder), meta | {"row_key": keys[r.row]}),
                total=n_sim) for r in todo]
    run_jobs(jobs, progress=progress, title="reference materials: simulating")
    write_json_atomic(out / "references.json", {"capture": str(cap.root), "frames": int(held.frames),
                                                "motion_key": motion_key(held), "seed": seed,
                                                "random_seeds": random_seeds(seed, random_draws),
                                                "rows": [r.row for r in refs], "folders": [r.folder for r in refs],
                                                "contact_offset_m": offset, "contact_offset": offset_info,
                                                "rest_shape": rest_shape, "rest_friction": rest_friction,
                                                "reused": done,
                                                "seconds": round(time.time() - t0, 1)})
    return out


def _row_key(av, material: Material, motion: Motion) -> str:
    """The content key of one reference row: the material asked for (before the rest-shape solve
    decides the model it is simulated in), the avatar's start (template, skinning, body shape,
    frame-1 pose, fps), the motion and whether a warm-up is under gravity (animate.warmup_without_gravity)."""
    from .animate import warmup_without_gravity

    t = av.template
    return content_key(t.vertices, t.faces, t.labels, t.boundary, t.rest_shape, av.body_weights, av.rest_rotations,
                       av.rest_translation, motion_key(motion), material=material.to_dict(),
                       shape=av.meta["body"]["shape"], fps=av.fps, bones=list(av.bone_names),
                       warmup_gravity=not warmup_without_gravity(material))


def _row_done(folder: Path, key: str, n_vertices: int) -> bool:
    """Whether ``folder`` holds a finished row made from ``key`` (its sequence.json, written last,
    records it; the vertices load)."""
    try:
        if read_json(folder / SEQUENCE_META).get("row_key") != key:
            return False
        return load_npz(folder / SEQUENCE_NPZ)["vertices"].shape[1] == n_vertices
    except (PhysavatarError, OSError, KeyError, ValueError):
        return False


def reference_row_job(avatar_dir, material: Material, motion: Motion, folder: str, meta: dict, report=None) -> dict:
    """One reference row as a :class:`physavatar.parallel.Job`: ``material`` on ``motion``
    (animate.animate_job), written to ``folder`` at once (``animate`` layout, no PLYs; sequence.json
    with ``meta`` and the model simulated, animate.simulated_material) through a temporary folder
    renamed into place. Returns the rest-shape report."""
    import shutil

    from .animate import animate_job, simulated_material, warmup_without_gravity

    V, rest = animate_job(avatar_dir, material, motion, report=report)
    av = Avatar.load(avatar_dir)
    t = av.template
    folder = Path(folder)
    tmp = folder.with_name(f".{folder.name}.partial")
    shutil.rmtree(tmp, ignore_errors=True)
    AnimatedSequence(V, t.faces, t.labels, None, av.fps, av.root).save(
        tmp, meta | {"material": simulated_material(material, rest).to_dict(), "rest_shape": rest,
                     "warmup_gravity": not warmup_without_gravity(material)}, ply=False)
    shutil.rmtree(folder, ignore_errors=True)
    tmp.rename(folder)
    return rest


def motion_key(m: Motion) -> str:
    """The content key (files.content_key) of a motion: rotations, root translation, fps, bones."""
    return content_key(m.rotations, m.root_translation, fps=float(m.fps), bones=list(m.bone_names))


def _reuse_references(path: Path, av, refs: list[Reference], n_frames: int, motion: Motion) -> tuple[dict, dict]:
    """Rows of a :func:`reference_sequences` folder, checked against this evaluation's materials
    (``refs``: :func:`_reference_materials`; the oracle is fitted in the run, not a reference)
    and held-out ``motion`` (unsliced). Returns (rows, stale): a row simulated on another motion
    (references.json's ``motion_key``: the capture's held-out motion changed since, or the
    folder predates the key), or whose material differs only in its contact thickness (a folder
    made with another --contact-offset, or before the draws had one), is not reused but listed
    in ``stale`` (row -> why), for the caller to simulate again; any other difference is an error.
    A row's material is this evaluation's when its sequence.json records the model that material
    is simulated in (animate.simulated_material of its recorded rest report: a draw asked for with
    the equilibrium rest whose garment was not at rest records the template)."""
    from .animate import simulated_material, warmup_count, warmup_without_gravity

    if not (path / "references.json").is_file():
        raise PhysavatarError(path, "no references.json (pass a `physavatar reference-sims` output folder)")
    ref_av = Avatar.load(path / "avatar")
    a, b = ref_av.template, av.template
    same = (a.vertices.shape == b.vertices.shape and np.allclose(a.vertices, b.vertices, atol=1e-7)
            and np.array_equal(a.faces, b.faces) and np.array_equal(a.labels, b.labels)
            and np.array_equal(a.boundary, b.boundary) and np.allclose(a.rest_shape, b.rest_shape, atol=1e-7)
            and np.allclose(ref_av.rest_rotations, av.rest_rotations) and np.allclose(ref_av.rest_translation, av.rest_translation)
            and ref_av.shape == av.shape)
    if not same:
        raise PhysavatarError(path / "avatar", "the references start from another template, shape or rest pose "
                              "than the evaluated avatar (made for another capture or avatar)")
    made = read_json(path / "references.json")
    n_made = int(made.get("frames", 0))
    if made.get("motion_key") is None or n_made > motion.frames or \
            made["motion_key"] != motion_key(motion.slice(0, n_made)):
        why = ("simulated on another held-out motion than the capture's" if made.get("motion_key") else
               "made before references recorded their motion")
        return {}, {r.row: why for r in refs}
    rows, stale = {}, {}
    warm = warmup_count(av, motion.slice(0, n_frames)) > 0
    for row, name, mat in refs:
        folder = path / name
        meta = read_json(folder / SEQUENCE_META) if (folder / SEQUENCE_META).is_file() else {}
        if meta.get("material") is None:
            raise PhysavatarError(folder, f"missing: no {row} sequence in this references folder")
        if warm and meta.get("warmup_gravity", True) != (not warmup_without_gravity(mat)):
            # session 34: animate's warm-up is weightless unless the rest shape is the equilibrium; a
            # row warmed up otherwise (or made before the warm-up recorded it) starts another motion
            stale[row] = "warmed up " + ("under gravity" if meta.get("warmup_gravity", True) else "without gravity") + \
                ", as this evaluation's rows are not"
            continue
        used = Material.from_dict(meta["material"])  # the model simulated (simulated_material)
        if used != mat and used == simulated_material(mat, meta.get("rest_shape") or {}):
            # ``mat`` itself: asked for with the equilibrium rest, its garment was not at rest in the
            # start frame, so it was simulated with the template, as it would be again (session 34:
            # evaluate simulated four of the foreign skirt's five draws again for this)
            used = mat
        if used != mat and dataclasses.replace(used, contact_offset=mat.contact_offset, rest_shape=mat.rest_shape,
                                               rest_friction=mat.rest_friction) == mat:
            # the estimate's model (thickness, rest shape, the rest solve's friction): simulated again
            stale[row] = (f"simulated with contact offset {1e3 * used.contact_offset:.3f} mm, rest shape "
                          f"{used.rest_shape!r} and rest friction {used.rest_friction}, the estimate's are "
                          f"{1e3 * mat.contact_offset:.3f} mm, {mat.rest_shape!r} and {mat.rest_friction}")
            continue
        if used != mat:
            differ = ", ".join(f"{f.name} {getattr(used, f.name)!r} against {getattr(mat, f.name)!r}"
                               for f in dataclasses.fields(mat) if getattr(used, f.name) != getattr(mat, f.name))
            raise PhysavatarError(folder / "sequence.json", f"{row} was simulated with another material than "
                                  f"this evaluation's ({differ}): other ground truth, --seed or --random-draws")
        rows[row] = _reuse_sequence(folder, av, n_frames).vertices
    return rows, stale


def _reuse_sequence(path, av, n_frames: int, material: Material | None = None, motion: Motion | None = None):
    """The ``animate`` output at ``path`` (checked against the avatar, the frame count and, when
    given, ``material`` and ``motion``: those its sequence.json records must be them)."""
    from .animate import check_sequence_motion
    path = Path(path)
    if not (path / SEQUENCE_NPZ).is_file():
        raise PhysavatarError(path, f"no {SEQUENCE_NPZ} (pass an `animate` output folder)")
    seq = AnimatedSequence.load(path)
    t = av.template
    if seq.vertices.shape[1] != len(t.vertices) or not np.array_equal(seq.faces, t.faces):
        raise PhysavatarError(path, f"sequence has {seq.vertices.shape[1]} vertices / other faces than the avatar "
                              f"({len(t.vertices)} vertices): not an animation of this avatar")
    if len(seq.vertices) < n_frames:
        raise PhysavatarError(path, f"sequence has {len(seq.vertices)} frames, the evaluation needs {n_frames}")
    if abs(seq.fps - av.fps) > 1e-6:
        raise PhysavatarError(path, f"sequence runs at {seq.fps} fps, the avatar at {av.fps}")
    meta = read_json(path / SEQUENCE_META) if (path / SEQUENCE_META).is_file() else {}
    used = meta.get("material")
    if material is not None and used is not None and Material.from_dict(used) != material:
        raise PhysavatarError(path / SEQUENCE_META, f"sequence was simulated with material {used.get('name')!r}, "
                              f"the avatar's is {material.name!r}: not an animation of this avatar")
    if motion is not None:
        check_sequence_motion(path / SEQUENCE_META, meta, av, motion)
    seq.vertices = seq.vertices[:n_frames]
    return seq
