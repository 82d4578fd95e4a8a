"""The garment's rest shape from static equilibrium (docs/physics.md "Session 27").

A captured garment's template is the garment *loaded*: hanging from its attachment under gravity
and resting on the body. Taken as the stress-free rest shape it sags again as soon as a simulation
starts. :func:`equilibrium_rest` finds the rest shape X̄ whose static equilibrium (gravity, the
boundary pinned where it is, contact with the body) is the template x₀:

    x_eq(X̄) = x₀,    x_eq(X̄) = the static equilibrium reached from x₀ with rest X̄.

The membrane's rest frames and areas, the hinges' rest angles and weights and the lumped masses
all come from X̄ (sim.mesh.ClothTopology). Solver: the fixed point X̄ ← X̄ − (x_eq(X̄) − x₀) of
inverse statics, accelerated with Anderson mixing (Walker & Ni 2011) over the last ``memory``
rounds. The fixed point takes ∂x_eq/∂X̄ as the identity, which is right for the stiff membrane
and bending in their own modes; the mixing fits the rest of the Jacobian from the rounds' secants
(a round that overshoots, error > 1.5 × the best, restarts it from the best round with a plain
step, halved on each restart that finds no better round), so no mixed derivative ∂²E/∂x∂X̄ (which the simulator does not have) is needed. Each round's
equilibrium (:func:`static_equilibrium`) is the simulator's own implicit step repeated with the
velocity reset to zero (a proximal-point iteration: every step minimises the static energy plus
½‖x − xₖ‖²_M / h², so it ends where the static energy is stationary), undamped, and frictionless,
or, for a material with ``rest_friction`` (session 36; ``fit-physics`` records it by default),
with *static* friction (:class:`StaticFriction`): Coulomb friction against the body anchored at
the start x₀ (the tangential displacement from x₀, not the step's, smoothed over the distance the
simulations treat as sticking, ε_v·dt), so the equilibrium is one in which every contact's
tangential force lies within μ × its normal force. Frictionless, a flared skirt resting on the
hips slides down them: its frictionless equilibrium is far from the start, and no rest shape near
the template holds it there (docs/physics.md "Issue 22, session 36").
"""

from __future__ import annotations

import dataclasses
import time

import numpy as np

from ..errors import PhysavatarError
from .contact import Friction
from .material import Material
from .settings import SimSettings

EQ_STEP = 5.0  # [s] the proximal step: nearly static (0.5 s left the plain top's hem creeping: 0.21 mm RMS against 0.10)
AT_REST_RMS = 5e-3  # [m] a start that no rest shape holds closer than this (RMS) is not at rest (is moving)
SAFEGUARD = 1.5  # a round whose error exceeds the best one's by this factor restarts the mixing from the best
MOVING_RMS = 20 * AT_REST_RMS  # [m] a first round (rest = x0) that drifts this far (RMS) from x0: a moving start
HOPELESS_RMS = 10 * AT_REST_RMS  # [m] three rounds with no better RMS error than this: no rest shape holds the start
STALLED_RMS = AT_REST_RMS  # [m] a best round above this (not at rest) that STALL_ROUNDS later rounds do not better: stalled
# (2 x AT_REST_RMS until session 34: the foreign skirt's draw 2 then ran 12 rounds, 600 s, for its round-4 best of 9.7 mm)
STALL_ROUNDS = 3
FLOOR_EXIT = 10  # an equilibrium step's Newton ends after this many line searches in a row at their floor
STOP_REASONS = {  # report["stopped"] -> what it says about the start (report["stop_reason"])
    "converged": "the rest shape found holds the start to the tolerance",
    "max_rounds": "the round limit was reached (the best round is kept)",
    "moving": f"the first round (the start as rest) drifted more than {1e3 * MOVING_RMS:.0f} mm RMS: a moving start",
    "hopeless": f"three rounds without one below {1e3 * HOPELESS_RMS:.0f} mm RMS: no rest shape holds the start",
    "stalled": f"the best round, not at rest (above {1e3 * STALLED_RMS:.0f} mm RMS), was not bettered in {STALL_ROUNDS} "
               "more rounds: the solve gave up (the rounds left were not tried)",
    "degenerate": "a round's rest shape had a degenerate triangle (the iteration went too far; the best round is kept)",
}


class StaticFriction(Friction):
    """Coulomb friction anchored at a fixed configuration: D(X − X₀) with ipctk's smoothed
    potential, the tangential *displacement* from ``anchor`` [N + Nb, 3] in place of a step's
    velocity (ĥ = 1, ε = ``eps_x`` [m]). Below ε a contact sticks (a spring of stiffness ~μλ/ε),
    beyond it it slides against μλ. Normal forces and tangent bases are lagged at each step's
    start, as the simulations' friction is. Its energy does not depend on the step length, so the
    near-static steps of :func:`static_equilibrium` end where gravity, elasticity, contact and
    this friction balance: a static equilibrium within the friction cone."""

    def __init__(self, scene, mu: float, eps_x: float, anchor: np.ndarray):
        super().__init__(scene, mu, eps_x, 1.0)
        self.anchor = np.asarray(anchor, np.float64)

    def begin_step(self, state):
        super().begin_step(state)
        self.dt, self.previous = 1.0, self.anchor


def rest_friction(material: Material, settings: SimSettings | None, friction: float | None = None) -> float:
    """The static-friction coefficient of the equilibrium: ``friction`` when given, else the
    simulations' (``settings.friction``) when ``material.rest_friction``, else 0 (frictionless)."""
    if friction is not None:
        return float(friction)
    return (settings or SimSettings()).friction if material.rest_friction else 0.0


def equilibrium_settings(settings: SimSettings | None, h: float, tol: float) -> SimSettings:
    """The settings of the equilibrium solve: ``settings``' contact model (d̂, d_min, self-contact,
    gravity, membrane model) without damping, implicit Euler with step ``h``, Newton to a step below
    ``tol`` / 10 [m] in every vertex. Its friction coefficient is ``settings``' (the solve anchors
    it: :class:`StaticFriction`)."""
    s = settings or SimSettings()
    return dataclasses.replace(s, dt=float(h), integrator="euler", damping_mass=0.0, friction_iterations=1,
                               damping_stiffness=0.0, newton_norm="max", newton_tol=0.1 * tol / h,
                               max_newton_iterations=max(s.max_newton_iterations, 200), keep_linearization=False)


def static_equilibrium(rest, faces, material: Material, x_start, boundary=(), body=None, body_faces=None,
                       settings: SimSettings | None = None, *, h: float = EQ_STEP, tol: float = 1e-5,
                       max_steps: int = 60, extra_terms=(), contact_exclude=None,
                       give_up_rms: float = np.inf, friction: float | None = None) -> tuple[np.ndarray, dict]:
    """The static equilibrium of the cloth with rest shape ``rest`` [N, 3], reached from
    ``x_start`` [N, 3] (v = 0): the boundary vertices stay at ``x_start``'s positions, the body
    ``body`` [Nb, 3] / ``body_faces`` (None: no body) is still. ``friction``: the Coulomb
    coefficient against the body, anchored at ``x_start`` (:class:`StaticFriction`; None:
    ``settings.friction`` when ``material.rest_friction``, else 0: frictionless). Implicit steps
    of length ``h`` with the velocity reset to zero after each (undamped; module docstring) until a
    step moves no vertex by more than ``tol`` [m], at most ``max_steps``, or until it is more than
    ``give_up_rms`` [m] (RMS) from ``x_start`` (info["gave_up"]). Returns (x [N, 3],
    {"steps", "last_move_m", "converged", "newton_iterations", "unconverged_steps"}): "converged"
    when the last step moved less than ``tol`` and its Newton solve converged; "unconverged_steps"
    counts steps whose Newton did not (iteration limit, or ``FLOOR_EXIT`` line searches in a row
    at their floor: no progress left)."""
    from .simulate import feasible_thickness
    from .solver import ClothSim

    s = equilibrium_settings(settings, h, tol)
    mu = rest_friction(material, settings, friction)
    s = dataclasses.replace(s, friction=mu)
    sim = ClothSim(rest, faces, material, s, boundary, extra_terms=extra_terms, contact_exclude=contact_exclude)
    x = np.array(x_start, dtype=np.float64)
    if body is not None:
        body = np.asarray(body, np.float64)
        sim.prepare(body, body_faces)
        if sim.dmin > 0:
            x, sim.settings = feasible_thickness(sim, x, body, body_faces)
        if mu > 0:  # anchored where the solve starts; sticking within what the simulations' steps treat as static
            base = settings or SimSettings()
            sim.friction = StaticFriction(sim.scene, mu, base.friction_eps_v * base.dt, np.vstack([x, body]))
    else:
        sim.prepare(None, None)
    targets = x[sim.boundary].copy() if len(sim.boundary) else None
    zero = np.zeros_like(x)
    info = {"steps": 0, "last_move_m": np.inf, "converged": False, "newton_iterations": 0}
    # the first step at the simulations' own step length sets the barrier stiffness κ as theirs is
    # set (ipctk's adaptive κ scales with mass / h²; it persists across steps): the contact then
    # holds the cloth at the distance theirs does
    sim.set_dt((settings or SimSettings()).dt)
    # a near-static step along a mode nothing stiff holds (a soft flare swinging in) can end its
    # Newton solve where the energy changes fall below round-off: every backtracking line search
    # then ends at its floor and the iterate stops moving; without this exit it repeated that to
    # max_newton_iterations (session 34: 3 of the foreign skirt's first 5 steps, 200 iterations each)
    sim.floor_exit = FLOOR_EXIT
    info["unconverged_steps"] = 0
    for k in range(max_steps):
        x_new, _, st = sim.step(x, zero, body, body, body_faces, targets)
        sim.set_dt(h)
        move = float(np.max(np.linalg.norm(x_new - x, axis=1))) if len(x) else 0.0
        info.update(steps=k + 1, last_move_m=move, newton_iterations=info["newton_iterations"] + st.newton_iterations)
        info["unconverged_steps"] += int(not st.converged)
        x = x_new
        if move < tol and k > 0:  # (not the first, short step)
            info["converged"] = bool(st.converged)  # a step that stopped moving because its Newton stalled is no equilibrium
            break
        if np.sqrt(np.mean(np.sum((x - x_start) ** 2, axis=1))) > give_up_rms:
            info["gave_up"] = True  # farther than ``give_up_rms`` (RMS) from the start: stopped there
            break
    return x, info


def _stalled(rms_mm: list[float]) -> bool:
    """Whether the rounds' RMS errors [mm] have stalled short of at rest: the best one is above
    ``STALLED_RMS`` and the last ``STALL_ROUNDS`` rounds did not better it. The start is then
    reported not at rest (report["at_rest"] false: the caller keeps the template). On the 24
    solves of session 34's foreign captures (docs/physics.md "Issue 22, session 34") no round
    after such a stall reached at rest, so stopping changed only the time; the report says that
    the rounds left were not tried (report["stopped"] "stalled")."""
    k = int(np.argmin(rms_mm))
    return rms_mm[k] > 1e3 * STALLED_RMS and len(rms_mm) - 1 - k >= STALL_ROUNDS


def _anderson(G: list[np.ndarray], F: list[np.ndarray], memory: int) -> np.ndarray:
    """Anderson mixing (type II, Walker & Ni 2011) of the fixed point g: the next iterate from the
    last rounds' g(Xₖ) (``G``) and residuals fₖ = g(Xₖ) − Xₖ (``F``), flat vectors."""
    m = min(memory, len(F) - 1)
    if m <= 0:
        return G[-1]
    dF = np.stack([F[-i] - F[-i - 1] for i in range(1, m + 1)], axis=1)
    dG = np.stack([G[-i] - G[-i - 1] for i in range(1, m + 1)], axis=1)
    gamma, *_ = np.linalg.lstsq(dF, F[-1], rcond=None)
    return G[-1] - dG @ gamma


def equilibrium_rest(x0, faces, material: Material, boundary=(), body=None, body_faces=None,
                     settings: SimSettings | None = None, *, tol: float = 1e-4, max_rounds: int = 12,
                     memory: int = 3, h: float = EQ_STEP, extra_terms=(), contact_exclude=None,
                     path=None, friction: float | None = None) -> tuple[np.ndarray, dict]:
    """The rest shape X̄ [N, 3] whose static equilibrium under gravity, pinned at ``boundary``
    and in contact with ``body`` (frame 0; None: no body), is the loaded shape ``x0`` [N, 3]
    (module docstring), to ``tol`` [m] in every vertex.

    ``material``: its density and stiffnesses (and contact offset) decide X̄; ``settings``: the
    contact model, gravity and friction coefficient of the simulations that will use it (damping
    is ignored: it vanishes at rest); the equilibria hold the garment with static friction of that
    coefficient when ``material.rest_friction`` (:func:`static_equilibrium`), frictionless
    otherwise; ``friction``: that coefficient instead.
    ``path``: the file named in the messages about bad input.
    Returns (X̄, report): report["converged"] says whether the tolerance was met within
    ``max_rounds`` (otherwise X̄ is the round with the smallest RMS error); "at_rest" whether
    the best round holds x₀ to an RMS error below ``AT_REST_RMS`` (5 mm; the solve stops at once when its
    first round, x₀ as rest, drifts more than ``MOVING_RMS``, 100 mm RMS, and after ``STALL_ROUNDS``
    rounds that do not better a best round above ``STALLED_RMS``, 5 mm RMS, i.e. not at rest): a garment that is moving in x₀
    (a capture that starts mid-motion) is in no static equilibrium, and callers then keep x₀ as
    the rest shape (garment_sim.equilibrium_part, fit-physics); "stopped" why the rounds ended
    (a key of ``STOP_REASONS``; "stop_reason" its words); "error_mm" per round (max and RMS of
    x_eq − x₀ over the vertices, the equilibrium's implicit steps, Newton iterations and seconds),
    "sag_mm": the first round's (X̄ = x₀), seconds.
    """
    x0 = np.asarray(x0, dtype=np.float64)
    F = np.asarray(faces, dtype=np.int64)
    b = np.unique(np.asarray(boundary, dtype=np.int64).reshape(-1))
    if x0.ndim != 2 or x0.shape[1] != 3 or not np.isfinite(x0).all():
        raise PhysavatarError(path, f"the garment for a rest shape must be finite vertices [N, 3], got {x0.shape}")
    if len(b) and (b.min() < 0 or b.max() >= len(x0)):
        raise PhysavatarError(path, f"boundary vertex ids out of range 0..{len(x0) - 1}")
    if body is None and not len(b):
        raise PhysavatarError(path, "a rest shape from static equilibrium needs something that holds the garment "
                                    "(boundary vertices or a body): this one would fall")
    if body is not None:
        from ..geometry import count_intersections

        body = np.asarray(body, np.float64)
        # crossings of the boundary's own edges and triangles do not count: the simulator has no
        # contact between prescribed vertices and the body (a coarse proxy's held triangle may cut
        # a convex shoulder; docs/physics.md, session 35)
        if count_intersections(x0, F, body, np.asarray(body_faces, np.int64).reshape(-1, 3), fixed=b):
            raise PhysavatarError(path, "the garment intersects the body in the frame its rest shape is solved for; "
                                        "it must start outside the body")
    t0 = time.perf_counter()
    free = np.ones(len(x0), bool)
    free[b] = False
    kw = dict(h=h, tol=0.1 * tol, extra_terms=extra_terms, contact_exclude=contact_exclude, friction=friction)
    mu = rest_friction(material, settings, friction)
    X = x0.copy()
    stopped = "max_rounds"  # why the rounds ended (report["stopped"])
    G, R = [], []  # the fixed point's g(X) = X − (x_eq(X) − x0) and residuals, flat
    best, history = (np.inf, X, np.zeros_like(X)), []
    alpha = 1.0  # the restarts' step length: halved on each restart without a better round in between
    for _ in range(max_rounds):
        t_round = time.perf_counter()
        try:
            x_eq, info = static_equilibrium(X, F, material, x0, b, body, body_faces, settings, **kw,
                                            give_up_rms=np.inf if history else MOVING_RMS)
        except PhysavatarError as e:  # a degenerate rest triangle (ClothTopology): the iteration went too far
            if not history:
                raise PhysavatarError(path, e.problem) from None
            stopped = "degenerate"
            break
        r = x_eq - x0
        d = np.linalg.norm(r[free], axis=1) if free.any() else np.zeros(1)
        err, rms = float(d.max()), float(np.sqrt(np.mean(d ** 2)))
        history.append({"max_mm": 1e3 * err, "rms_mm": 1e3 * rms,
                        "steps": info["steps"], "equilibrium_converged": info["converged"],
                        "newton_iterations": info.get("newton_iterations"),
                        "unconverged_steps": info.get("unconverged_steps"),
                        "seconds": round(time.perf_counter() - t_round, 2)})
        if err < tol:
            best, stopped = (rms, X.copy(), r), "converged"
            break
        if info.get("gave_up") or (len(history) >= 3 and min(e["rms_mm"] for e in history) > 1e3 * HOPELESS_RMS):
            if rms < best[0]:
                best = (rms, X.copy(), r)
            stopped = "moving" if info.get("gave_up") else "hopeless"
            break  # hopeless: the start is far from any static equilibrium (report["at_rest"])
        if _stalled([e["rms_mm"] for e in history]):
            stopped = "stalled"
            break  # far from at rest and no better round for STALL_ROUNDS rounds (the demo's draw: 12 rounds, 573 s)
        if rms > SAFEGUARD * best[0]:  # overshot: a shorter plain step from the best round, history cleared
            G, R = [], []
            alpha *= 0.5  # (the same step again would repeat the same round: session 28's dress stalled so)
            X = best[1] - alpha * best[2]
        else:
            if rms < best[0]:  # the best round by RMS (a few hem vertices can stall the max)
                best, alpha = (rms, X.copy(), r), 1.0
            G.append((X - r).ravel())
            R.append(-r.ravel())
            G, R = G[-(memory + 1):], R[-(memory + 1):]
            X = _anderson(G, R, memory).reshape(X.shape)
        X[~free] = x0[~free]
    _, X, r = best
    sag = history[0]
    d = np.linalg.norm(r[free], axis=1) if free.any() else np.zeros(1)
    err, rms = float(d.max()), float(np.sqrt(np.mean(d ** 2)))
    report = {"converged": bool(err < tol), "at_rest": bool(rms < AT_REST_RMS), "tol_mm": 1e3 * tol,
              "rounds": len(history), "stopped": stopped, "stop_reason": STOP_REASONS[stopped], "error_mm": history,
              "sag_mm": {"max": sag["max_mm"], "rms": sag["rms_mm"]}, "final_max_mm": 1e3 * err,
              "final_rms_mm": 1e3 * rms,
              "rest_offset_mm": {"max": 1e3 * float(np.linalg.norm(X - x0, axis=1).max()),
                                 "rms": 1e3 * float(np.sqrt(np.mean(np.sum((X - x0) ** 2, axis=1))))},
              "method": f"fixed point with Anderson mixing (memory {memory}); equilibrium: implicit steps of "
                        f"{h:g} s from rest, " + (f"static friction {mu:g} anchored at the start"
                                                  if mu > 0 and body is not None else "frictionless"),
              "friction": mu if body is not None else 0.0, "seconds": round(time.perf_counter() - t0, 2)}
    return X, report


def describe(report: dict, subject: str) -> str:
    """One line on an :func:`equilibrium_rest` solve of ``subject`` (e.g. "the template"): what it
    reached and, when it did not converge, why it stopped."""
    why = "" if report.get("stopped") in (None, "converged") else f"; stopped: {report['stop_reason']}"
    return (f"rest shape from static equilibrium: {subject} sags {report['sag_mm']['max']:.2f} mm (max) with itself "
            f"as rest, {report['final_max_mm']:.3f} mm ({report['final_rms_mm']:.3f} RMS) with the rest found "
            f"({report['rounds']} rounds, {report['seconds']:.1f} s{why})")
