"""The material stage: :func:`run` (``physavatar fit-physics``, and ``physavatar run``'s physics step)."""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Callable
from pathlib import Path

import numpy as np

from ...data.material import resolve_material
from ...errors import PhysavatarError
from ...files import write_json_atomic
from ...progress import resolve
from ..base import to_dict
from .config import PhysicsConfig
from .data import clear_start, load_physics_data
from .outputs import FitResult, write_outputs
from .parameters import EXACT_ITERATIONS, PAPER_ITERATIONS, SHAPE_WEIGHT, SHAPE_WEIGHTS, far_material, fit_settings
from .proxy import make_proxy, on_proxy
from .select import MODELS, fit_material

log = logging.getLogger(__name__)


def run(source: Path, *, out: Path, config: PhysicsConfig, progress=None,
        say: Callable[[str], None] | None = None) -> FitResult:
    """Fit the cloth material of the garment in ``source`` and write it to ``out``.

    ``source``: a tracked folder, a capture with ground-truth meshes, or a garment sequence
    (:func:`~.data.load_physics_data`). The window ``config.start`` … ``+ config.window`` is
    simulated from its first frame, made a valid start (:func:`~.data.clear_start`), on a coarse
    proxy when the garment has more than ``config.max_vertices`` vertices, against the reference
    with ``config.noise_mm`` of noise. ``out`` gets material.json, fit_log.csv, fit.png
    (:func:`~.outputs.write_outputs`) and config.json (the config and the source).

    ``progress``: anything :func:`physavatar.progress.resolve` accepts (one task, "fit", advanced
    per iteration with its loss and RMS distance). ``say(line)``: what the command prints
    besides (notes on the input, the proxy, one line per iteration; default: this module's
    logger). Returns the :class:`~.outputs.FitResult` (its ``start_state`` and ``proxy`` say what
    was done to the input).
    """
    say = say or log.info
    source, out = Path(source), Path(out)
    cfg = config
    initial = far_material() if cfg.init == "far" else resolve_material(cfg.init)
    if cfg.density is not None:
        initial = dataclasses.replace(initial, density=cfg.density)
    if cfg.rest_friction and cfg.rest_shape == "equilibrium":
        initial = dataclasses.replace(initial, rest_friction=True)
    sequence = load_physics_data(source)
    if cfg.start < 0 or cfg.start + 2 > sequence.frames:
        raise PhysavatarError(None, f"option --start: must leave at least 2 of the {sequence.frames} frames")
    if not len(sequence.boundary):
        say("note: the garment has no boundary (attached) vertices: it is simulated as held by contact and "
            "friction alone" + (" (and --friction is 0)" if cfg.friction == 0 else ""))
    # the shape term's weight chosen by the frames after the window (session 36): they are carried
    # through the start, proxy and thickness with the window, and left out of the fit
    weights, held = shape_weights(cfg, sequence.frames, say)
    # the simulation starts from the tracked frame `start` at rest; IPC needs it outside the body
    data, start_info = clear_start(sequence.window(cfg.start, cfg.window + held), source, cfg.start, sequence)
    if start_info["pushed_vertices"]:
        say(f"note: frame {cfg.start} has the garment {start_info['crossing_pairs']} triangle pairs through the "
            f"body / {start_info['min_gap_mm']:.2f} mm from it: {start_info['pushed_vertices']} vertices pushed "
            f"out (at most {start_info['max_push_mm']:.1f} mm) to start the simulations")
    proxy = None
    fine, fine_start = data, data.initial
    n_fine = data.reference.shape[1]
    if cfg.max_vertices and n_fine > cfg.max_vertices:
        proxy = make_proxy(data.rest, data.faces, data.boundary, cfg.max_vertices)
        data = on_proxy(data, proxy)
        say(f"simulating a {len(proxy.vertices)}-vertex proxy of the {n_fine}-vertex garment "
            f"(mean edge {100 * proxy.mean_edge:.1f} cm, {len(proxy.boundary)} boundary vertices)")
    # the contact thickness: estimated on the garment itself, the start it needs on what is simulated
    offset, offset_info = contact_offset(cfg.contact_offset, dataclasses.replace(fine, initial=fine_start))
    thickness, offset_info["start"], data = thickness_start(offset, data)
    offset_info["offset_mm"] = 1e3 * thickness
    start_info["contact_offset"] = offset_info
    initial = dataclasses.replace(initial, contact_offset=thickness)
    if thickness > 0:
        lifted = offset_info["start"].get("lifted_vertices", 0)
        say(f"note: contact offset {1e3 * thickness:.2f} mm ({offset_info.get('method', 'given')}"
            + (f": the garment rests {offset_info['resting_mm']:.2f} mm from the body" if "resting_mm" in offset_info
               else "")
            + (f"; {lifted} start vertices lifted, at most {offset_info['start']['max_lift_mm']:.1f} mm" if lifted
               else "") + ")")
    # benchmark noise perturbs what is fitted to, not the (template-clean) start state
    following = data.with_noise(cfg.noise_mm * 1e-3, cfg.seed + 1) if held else None
    data = data.window(0, cfg.window).with_noise(cfg.noise_mm * 1e-3, cfg.seed)
    n_iter = cfg.iterations or (PAPER_ITERATIONS if cfg.gradient == "fd" else EXACT_ITERATIONS)
    say(f"fitting {('rho, ' if cfg.fit_density else '') + 'ks, kb'} of a {data.reference.shape[1]}-vertex "
        f"garment over {data.frames} frames ({cfg.gradient} gradients, up to {n_iter} iterations)")
    rows = ((n_iter + (1 if cfg.gradient == "exact" else 0)) * (len(MODELS) if cfg.selects_integrator else 1)
            * (2 if cfg.rest_shape == "equilibrium" else 1) * len(weights))
    with resolve(progress).task("fit", total=rows) as task:

        def report(row):
            task.advance(loss=row["loss"], rms_mm=row["rms_mm"])
            # one line per iteration: a bar alone shows nothing when output is not a terminal
            say(f"{iteration_line(row)}  {row['wall_time_s']:.0f} s")

        settings = fit_settings(friction=cfg.friction, newton_tol=cfg.newton_tol, integrator=cfg.fitting_integrator)

        candidates = []
        for w in weights:
            if len(weights) > 1:
                say(f"fitting with shape weight {w:g}")

            def fit(d, init, w=w):
                return fit_material(d, init, cfg.gradient, cfg.iterations, cfg.fit_density, settings,
                                    workers=cfg.workers, substeps=cfg.substeps, callback=report, shape_weight=w,
                                    select_integrator=cfg.selects_integrator)

            result, rest, rest_report = fit(data, initial), data.rest, None
            if cfg.rest_shape == "equilibrium":
                result, rest_report, rest = refit_at_equilibrium(data, result, settings, fit, say)
            candidates.append((result, rest, rest_report))
        chosen = 0
        if len(candidates) > 1:
            chosen, selection = select_shape_weight(following, candidates, weights, cfg.window, settings,
                                                    cfg.substeps, say)
        result, _, rest_report = candidates[chosen]
        if len(candidates) > 1:
            result.shape_selection = selection
        if rest_report is not None:
            start_info["rest_shape"] = rest_report
        if result.material.rest_shape != "equilibrium":  # (kept the first fit: no rest solve in its model)
            result.material = dataclasses.replace(result.material, rest_friction=False)
    result.start_state = start_info
    if proxy is not None:
        result.proxy = {"vertices": len(proxy.vertices), "faces": len(proxy.faces), "boundary": len(proxy.boundary),
                        "mean_edge_m": proxy.mean_edge, "garment_vertices": n_fine, "max_vertices": cfg.max_vertices}
    write_outputs(out, result)
    write_json_atomic(out / "config.json", {**to_dict(cfg), "source": str(source.resolve())})
    return result


SIGN_LEVEL = 0.05  # select_shape_weight: the sign test's level for leaving the default weight


def shape_weights(cfg: PhysicsConfig, frames: int, say) -> tuple[tuple, int]:
    """The shape weights to fit with and the frames after the window held out to choose between
    them: (``(cfg.shape_weight,)``, 0) unless ``cfg.select_shape_weight`` with exact gradients and
    no ``--shape-weight`` given; then (:data:`SHAPE_WEIGHTS`, up to a window's length of the frames
    after the window, at least 2: without them the default weight alone, with a note)."""
    if not (cfg.select_shape_weight and cfg.shape_weight is None and cfg.gradient == "exact"):
        return (cfg.shape_weight,), 0
    held = min(cfg.window, frames - cfg.start - cfg.window)
    if held < 2:
        say(f"note: fewer than 2 frames after the window: the shape weight is not chosen (kept {SHAPE_WEIGHT:g})")
        return (None,), 0
    return SHAPE_WEIGHTS, held


def select_shape_weight(following, candidates, weights, window: int, settings, substeps: int, say):
    """The fit (index into ``candidates``: (result, rest shape, rest report) per weight of
    ``weights``, the first the default) whose material, simulated from the window's start through
    the frames after it (``following``: the window and those frames, in the fit's model and with its
    rest shape), predicts those frames best. The shape term makes the fit prefer a cloth that keeps
    the reference's local shape; whether that predicts new motion depends on how the reference was
    made (tracked meshes keep the template's local shape: docs/physics.md "Issue 22, session 36"),
    so the prediction of frames the fit did not see decides, as it would decide any setting of the
    model. Tracking error is as large as the differences compared on some captures, so the default
    is left only on evidence: another weight is kept when its RMS distance to the frames after the
    window is smaller *and* it is closer in so many of those frames that a one-sided sign test
    rejects "each frame a coin toss" at :data:`SIGN_LEVEL` (5 %; k of n frames closer,
    P(≥ k | ½) < 0.05: at least 5 of 5, 6 of 6 or 7, 7 of 8, 9 of 12; never with 4 or fewer frames).
    Returns (index, record for material.json)."""
    from scipy.stats import binomtest

    from .objective import rollout

    rows = []
    for w, (result, rest, _) in zip(weights, candidates):
        d = dataclasses.replace(following, rest=rest)
        run_ = rollout(d, result.material, dataclasses.replace(settings, integrator=result.material.integrator),
                       substeps=substeps)
        err = run_.positions[window:] - d.reference[window:]
        sq = np.sum(err * err, axis=-1)  # [frames, V]
        rms = 1e3 * float(np.sqrt(np.mean(sq)))
        per_frame = 1e3 * np.sqrt(np.mean(sq, axis=-1))
        rows.append({"shape_weight": w if w is not None else SHAPE_WEIGHT, "heldout_rms_mm": rms,
                     "heldout_rms_mm_per_frame": [round(float(v), 4) for v in per_frame],
                     "fit_rms_mm": result.rms_mm, "stretch_ratio": result.material.stretch_ratio,
                     "bend_ratio": result.material.bend_ratio, "integrator": result.material.integrator,
                     "converged": bool(run_.converged), "material": result.material.to_dict()})
        say(f"shape weight {rows[-1]['shape_weight']:g}: predicts the {len(err)} frames after the window to "
            f"{rms:.2f} mm RMS (fit {result.rms_mm:.2f} mm; ks/rho {result.material.stretch_ratio:.4g}, "
            f"kb/rho {result.material.bend_ratio:.3g})")
    base = np.asarray(rows[0]["heldout_rms_mm_per_frame"])
    for r in rows[1:]:
        closer = int(np.sum(np.asarray(r["heldout_rms_mm_per_frame"]) < base))
        r["frames_closer_than_default"] = closer
        r["sign_test_p"] = float(binomtest(closer, len(base), 0.5, alternative="greater").pvalue)
    better = [i for i, r in enumerate(rows) if i and r["heldout_rms_mm"] < rows[0]["heldout_rms_mm"]
              and r["sign_test_p"] < SIGN_LEVEL]
    chosen = min(better, key=lambda i: rows[i]["heldout_rms_mm"]) if better else 0
    for r in rows[1:]:
        say(f"shape weight {r['shape_weight']:g} is closer in {r['frames_closer_than_default']} of {len(base)} frames "
            f"(sign test p = {r['sign_test_p']:.3f})")
    say(f"kept shape weight {rows[chosen]['shape_weight']:g}")
    return chosen, {"chosen": rows[chosen]["shape_weight"], "frames_after_window": len(err), "fits": rows,
                    "criterion": "the default weight unless another predicts the tracked frames after the window, "
                                 "simulated on from the window's start, with a smaller RMS distance and closer in "
                                 f"enough frames for a one-sided sign test at {SIGN_LEVEL:g} (docs/physics.md "
                                 "'Issue 22, session 36')"}


def refit_at_equilibrium(data, first, settings, fit, say) -> tuple[object, dict, np.ndarray]:
    """The fit again with the rest shape whose static equilibrium (for the material of the
    ``first`` fit, on the window's first body frame) is the start frame (sim.rest.equilibrium_rest),
    from that material; ``fit(data, initial)`` is the first fit's call. Returns (the second fit's
    result, its material recording rest_shape "equilibrium"; report: the solve, the first fit's
    RMS and material, and how far the rest shape for the final material is from the one fitted
    with: the start frame's sag in the final material with the rest fitted with, ``refit_sag_mm``;
    the rest shape the returned fit was made with). A start frame that is not at rest (sim.rest:
    the garment moves in it) keeps the first fit (report["used"] false; its material records the
    template rest shape)."""
    from ...sim.rest import describe, equilibrium_rest, static_equilibrium

    x0 = data.reference[0] if data.initial is None else data.initial
    body = None if data.collider is None else data.collider[0]
    mat = dataclasses.replace(first.material, rest_shape="equilibrium")
    rest, report = equilibrium_rest(x0, data.faces, mat, data.boundary, body, data.collider_faces, settings)
    line = describe(report, "the start frame")
    if not report["at_rest"]:  # the garment moves in the start frame: no static equilibrium is it
        say(f"note: {line}: the start frame is not at rest; the fit with it as rest shape is kept")
        return first, report | {"used": False}, data.rest
    say(line + "; fitting again from the first fit's material")
    result = fit(dataclasses.replace(data, rest=rest), mat)
    x_eq, _ = static_equilibrium(rest, data.faces, result.material, x0, data.boundary, body, data.collider_faces,
                                 settings)
    report |= {"first_fit": {"rms_mm": first.rms_mm, "stretch_ratio": first.material.stretch_ratio,
                             "bend_ratio": first.material.bend_ratio},
               "refit_sag_mm": 1e3 * float(np.linalg.norm(x_eq - x0, axis=1).max()), "used": True}
    return result, report, rest


def contact_offset(given: float | None, data) -> tuple[float, dict]:
    """The fit's contact thickness [m]: ``given``, or (None) estimated from the window's first
    frame (sim.offset.estimate_contact_offset; 0 without a body). Returns (offset, report)."""
    from ...sim import SimSettings
    from ...sim.offset import estimate_contact_offset

    x0 = data.reference[0] if data.initial is None else data.initial  # the start (clear_start)
    return _given_or_estimated(given, data.collider is not None, lambda: estimate_contact_offset(
        x0, data.faces, data.collider[0], data.collider_faces, data.boundary, SimSettings().dhat))


def _given_or_estimated(given: float | None, has_body: bool, estimate) -> tuple[float, dict]:
    """(offset, report): 0 without a body or when ``given`` is 0, ``given`` when set, else
    ``estimate()`` (sim.offset.estimate_contact_offset on some frame)."""
    if not has_body or given == 0:
        return 0.0, {"method": "given" if given == 0 else "no body", "offset_mm": 0.0}
    if given is not None:
        return float(given), {"method": "given", "offset_mm": 1e3 * float(given)}
    return estimate()


def template_contact_offset(template, given: float | None = None) -> tuple[float, dict]:
    """The contact thickness [m] a fit of this capture will use, from its template alone (frame 1,
    where `run`'s tracking and the fit start): ``given`` (``--contact-offset``), or estimated on the
    template's first garment against its body as :func:`contact_offset` estimates it on the
    fit's start frame. `reference-sims` gives it to the random draws, simulated before any fit,
    so that they are simulated in the model the estimate is (evaluate checks it against the
    avatar's). Returns (offset, report)."""
    import numpy as np

    from ...geometry import submesh
    from ...sim import SimSettings
    from ...sim.offset import estimate_contact_offset

    labels = np.asarray(template.labels)
    garments = sorted(set(labels.tolist()) - {0})

    def estimate():
        gidx, gfaces = submesh(template.faces, labels == garments[0])
        bidx, bfaces = submesh(template.faces, labels == 0)
        V = np.asarray(template.vertices, np.float64)
        return estimate_contact_offset(V[gidx], gfaces, V[bidx], bfaces, np.flatnonzero(template.boundary[gidx]),
                                       SimSettings().dhat)

    return _given_or_estimated(given, bool(garments) and bool((labels == 0).any()), estimate)


def thickness_start(offset: float, data) -> tuple[float, dict, object]:
    """The start ``data`` needs for the thickness ``offset`` (sim.offset.feasible_start: lifted
    where a contact pair is closer than d̂/2 beyond it, the thickness lowered where it could not
    be; the rest shape moved with it). Returns (thickness, report, data with that start)."""
    from ...sim import SimSettings
    from ...sim.offset import feasible_start

    if offset <= 0 or data.collider is None:
        return offset, {}, data
    x0 = data.reference[0] if data.initial is None else data.initial
    x, thickness, report = feasible_start(x0, data.faces, data.collider[0], data.collider_faces, offset,
                                          SimSettings().dhat, data.boundary)
    # the rest shape moves with the start, as the proxy's does (the lift adds no strain)
    rest = None if data.rest is None else data.rest + (x - x0)
    return thickness, report, dataclasses.replace(data, initial=x, rest=rest)


def iteration_line(row: dict) -> str:
    """One iteration of a fit's history as the command prints it."""
    params = "  ".join(f"{k}={row[k]:.4g}" for k in ("density", "stretch_stiffness", "bend_stiffness", "bdf2_blend")
                       if k in row)
    line = f"it {row['iteration']:3d}  loss {row['loss']:.4g} m² ({row['rms_mm']:.2f} mm)  {params}"
    if "integrator" in row:
        line += f"  [{row['integrator']}]"
    return line
