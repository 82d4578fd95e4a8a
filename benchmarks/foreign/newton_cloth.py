"""A garment on a moving body, simulated by NVIDIA Newton's VBD cloth solver (``pip install newton``).

Independent of physavatar.sim: Newton's vertex block descent (Chen et al. 2024) with its own
models. Membrane: Newton's stable Neo-Hookean triangle (Lamé μ = ``tri_ke``, λ = ``tri_ka`` in
N/m); bending: Newton's dihedral-angle hinge, energy ½ k ℓ (θ − θ̄)² with k = ``edge_ke`` [N];
contact with the body: penalty springs between particles (radius r) and the body's triangle mesh
(``soft_contact_ke`` [N/m], damping ``soft_contact_kd``, Coulomb friction μ), the body being one
static Newton mesh shape whose points and per-vertex velocities are rewritten every substep (the
body interpolated linearly within a frame) and whose BVH is refitted. Pinned garment vertices
(waistband, straps) are inactive particles moved to their targets every substep.

Warp runs its kernels on the CPU here; the first use compiles them (cached in ~/.cache/warp).
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np


def available() -> bool:
    try:
        import newton  # noqa: F401
        import warp  # noqa: F401
    except ImportError:
        return False
    return True


@dataclasses.dataclass(frozen=True)
class Fabric:
    """A fabric in Newton's terms. density ρ [kg/m²]; tri_ke = μ, tri_ka = λ [N/m] (2-D Lamé
    constants of the membrane); edge_ke [N] hinge stiffness per unit edge length; tri_kd, edge_kd:
    Newton's damping coefficients."""

    density: float = 0.2
    tri_ke: float = 2.0e3
    tri_ka: float = 2.0e3
    edge_ke: float = 5.0e-3
    tri_kd: float = 1.0e-6
    edge_kd: float = 1.0e-6

    @staticmethod
    def from_physical(density: float, stretch: float, bend: float, poisson: float, edge_length: float,
                      stretch_scale: float = 1.0) -> Fabric:
        """The closest Newton fabric to an isotropic shell (ρ, κs = E·t [N/m], κb = D [N·m], ν).

        Membrane: plane-stress Lamé constants μ = κs / (2(1+ν)), λ = κs ν / (1−ν²) (λ is kept
        ≥ 0.1 μ: Newton's stable Neo-Hookean needs λ > 0 for its rest-stress shift α = 1 + μ/λ).
        ``stretch_scale`` multiplies both (VBD converges slowly on very soft membranes).
        Bending: the discrete-shell hinge energy (κb/2)·3ℓ²/(A₁+A₂)·θ² of an equilateral mesh
        (Grinspun et al. 2003), equated with Newton's ½ k ℓ θ², gives k = 3 κb ℓ / (A₁+A₂)
        = 3 κb / (√3/2 ℓ) for the mean edge length ℓ.
        """
        mu = stretch / (2 * (1 + poisson)) * stretch_scale
        lam = max(stretch * poisson / (1 - poisson ** 2) * stretch_scale, 0.1 * mu)
        k = 3 * bend / (math.sqrt(3) / 2 * edge_length)
        return Fabric(density=density, tri_ke=mu, tri_ka=lam, edge_ke=k)


@dataclasses.dataclass(frozen=True)
class NewtonSettings:
    """substeps per frame; VBD iterations per substep; contact: penalty stiffness [N/m] and
    damping, friction μ, particle radius [m] (the cloth's contact thickness), margin [m] of the
    contact search; gravity [m/s²] along z; self_contact: Newton's cloth self-contact."""

    substeps: int = 10
    iterations: int = 10
    contact_ke: float = 1.0e4
    contact_kd: float = 1.0e-2
    friction: float = 0.3
    radius: float = 6.0e-3
    margin: float = 1.0e-2
    gravity: float = -9.81
    self_contact: bool = False
    device: str = "cpu"


def _quiet():
    import warp as wp

    wp.config.quiet = True
    wp.config.verbose = False
    wp.init()
    return wp


class ClothOnBody:
    """Cloth (vertices [N, 3], faces [F, 3]) with ``pinned`` vertex ids, on a body mesh.

    ``body_vertices`` [Nb, 3] / ``body_faces`` [Fb, 3]: the body's first pose (outward CCW
    faces). Call :meth:`advance` once per frame with the body's next pose and the pinned
    vertices' next targets; ``positions`` is the cloth's state.
    """

    def __init__(self, vertices, faces, pinned, body_vertices, body_faces, fabric: Fabric = Fabric(),
                 settings: NewtonSettings = NewtonSettings()):
        wp = _quiet()
        import newton

        self.wp, self.settings = wp, settings
        V = np.asarray(vertices, np.float32)
        F = np.asarray(faces, np.int32)
        self.n = len(V)
        self.pinned = np.asarray(pinned, np.int64)
        builder = newton.ModelBuilder(up_axis=newton.Axis.Z, gravity=(0.0, 0.0, settings.gravity))
        self.body_mesh = None
        if body_vertices is not None:
            BV = np.asarray(body_vertices, np.float32)
            self.body_mesh = newton.Mesh(BV, np.asarray(body_faces, np.int32).ravel(), compute_inertia=False,
                                         is_solid=True)
            cfg = newton.ModelBuilder.ShapeConfig(mu=settings.friction, ke=settings.contact_ke,
                                                  kd=settings.contact_kd, has_shape_collision=False)
            builder.add_shape_mesh(-1, mesh=self.body_mesh, cfg=cfg)
        builder.add_cloth_mesh(pos=wp.vec3(0.0, 0.0, 0.0), rot=wp.quat_identity(), scale=1.0,
                               vel=wp.vec3(0.0, 0.0, 0.0), vertices=[wp.vec3(*p) for p in V],
                               indices=F.ravel().tolist(), density=fabric.density, tri_ke=fabric.tri_ke,
                               tri_ka=fabric.tri_ka, tri_kd=fabric.tri_kd, edge_ke=fabric.edge_ke,
                               edge_kd=fabric.edge_kd, particle_radius=settings.radius)
        builder.color(include_bending=True)
        model = builder.finalize(device=settings.device)
        model.soft_contact_ke = settings.contact_ke
        model.soft_contact_kd = settings.contact_kd
        model.soft_contact_mu = settings.friction
        if self.body_mesh is not None:
            # The body moves inside a static shape: make its broad-phase box the whole scene.
            big = 50.0
            model.shape_collision_aabb_lower.assign(np.full((model.shape_count, 3), -big, np.float32))
            model.shape_collision_aabb_upper.assign(np.full((model.shape_count, 3), big, np.float32))
        flags = model.particle_flags.numpy()
        flags[self.pinned] &= ~int(newton.ParticleFlags.ACTIVE)
        model.particle_flags.assign(flags)
        self.model = model
        self.solver = newton.solvers.SolverVBD(model, iterations=settings.iterations,
                                               particle_enable_self_contact=settings.self_contact,
                                               particle_self_contact_margin=settings.radius * 1.5,
                                               particle_self_contact_gap=settings.radius)
        self.s0, self.s1 = model.state(), model.state()
        self.control = model.control()
        self.pipeline = newton.CollisionPipeline(model, soft_contact_gap=settings.margin) \
            if self.body_mesh is not None else None
        self.contacts = self.pipeline.contacts() if self.pipeline is not None else None
        self._body = None if body_vertices is None else np.asarray(body_vertices, np.float32)
        self._pins = V[self.pinned].copy()

    @property
    def positions(self) -> np.ndarray:
        return self.s0.particle_q.numpy().astype(np.float64)[: self.n]

    @property
    def velocities(self) -> np.ndarray:
        return self.s0.particle_qd.numpy().astype(np.float64)[: self.n]

    def damp(self, keep: float) -> None:
        """Multiply every particle velocity by ``keep`` (the settle's drag; the fabric's own
        damping, tri_kd / edge_kd, is left as it is)."""
        qd = self.s0.particle_qd.numpy()
        qd *= keep
        self.s0.particle_qd.assign(qd)

    def advance(self, frame_dt: float, body_next=None, pins_next=None) -> np.ndarray:
        """One frame of ``settings.substeps`` VBD steps towards the given body pose and pin targets
        (both linearly interpolated within the frame); returns the positions [N, 3]."""
        st = self.settings
        h = frame_dt / st.substeps
        body0 = self._body
        body1 = body0 if body_next is None else np.asarray(body_next, np.float32)
        pins0 = self._pins
        pins1 = pins0 if pins_next is None else np.asarray(pins_next, np.float32)
        vel = None if body0 is None else (body1 - body0) / frame_dt
        wm = None if self.body_mesh is None else self.body_mesh.mesh
        for k in range(st.substeps):
            a = (k + 1) / st.substeps
            if wm is not None:
                wm.points.assign((1 - a) * body0 + a * body1)
                wm.velocities.assign(vel)
                wm.refit()
            if len(self.pinned):
                q = self.s0.particle_q.numpy()
                qd = self.s0.particle_qd.numpy()
                q[self.pinned] = (1 - a) * pins0 + a * pins1
                qd[self.pinned] = (pins1 - pins0) / frame_dt
                self.s0.particle_q.assign(q)
                self.s0.particle_qd.assign(qd)
            self.s0.clear_forces()
            if self.pipeline is not None:
                self.pipeline.collide(self.s0, self.contacts)
            self.solver.step(self.s0, self.s1, self.control, self.contacts, h)
            self.s0, self.s1 = self.s1, self.s0
        self._body, self._pins = body1, pins1
        return self.positions


def simulate_sequence(vertices, faces, pinned, pin_targets, body_sequence, body_faces, fps: float,
                      fabric: Fabric = Fabric(), settings: NewtonSettings = NewtonSettings(), settle_frames: int = 0,
                      on_frame=None, settle_damping: float = 1.0, info: dict | None = None) -> np.ndarray:
    """[T, N, 3] cloth positions along a body sequence [T, Nb, 3] (frame 0: the rest pose the
    cloth was made for) with pinned vertices following ``pin_targets`` [T, K, 3].

    ``settle_frames`` frames are first simulated at frame 0's pose (the garment drapes); frame 0
    of the result is the settled state. ``settle_damping`` < 1 multiplies the velocities by it
    after every settle frame (a drag that only the drape feels), so the garment comes to rest:
    the fabric's own damping is nearly nil, and an undamped drape still swings after seconds
    (the flared skirt: about 2.7 mm per frame after 60 frames). ``info`` (a dict) receives
    ``settle_drift_mm``: the mean vertex displacement [mm] of the last settle frame.
    ``on_frame(f, x)`` is called for each frame."""
    sim = ClothOnBody(vertices, faces, pinned, body_sequence[0], body_faces, fabric, settings)
    dt = 1.0 / fps
    x = sim.positions
    drift = 0.0
    for _ in range(settle_frames):
        x_new = sim.advance(dt)
        if settle_damping < 1.0:
            sim.damp(settle_damping)
        drift, x = float(np.linalg.norm(x_new - x, axis=1).mean()), x_new
    if info is not None:
        info["settle_drift_mm"] = 1e3 * drift
    out = np.empty((len(body_sequence), sim.n, 3))
    out[0] = sim.positions
    if on_frame is not None:
        on_frame(0, out[0])
    for f in range(1, len(body_sequence)):
        out[f] = sim.advance(dt, body_sequence[f], pin_targets[f])
        if on_frame is not None:
            on_frame(f, out[f])
    return out
