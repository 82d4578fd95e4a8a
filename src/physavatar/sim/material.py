"""Cloth material: area density, membrane and bending stiffness in SI units.

PhysAvatar (Sec. 3.2) estimates three scalars per garment: density ρ, membrane stiffness κs and
bending stiffness κb. Here they carry units so that a fitted material means the same thing to
every caller:

- ``density``            ρ  [kg/m²]  mass per unit rest area (lumped to vertices),
- ``stretch_stiffness``  κs [N/m]    Young's modulus × thickness of the shell (membrane),
- ``bend_stiffness``     κb [N·m]    flexural rigidity of the shell (hinge bending),
- ``poisson``            ν  [-]      Poisson ratio of the membrane (a setting, not estimated).

Every elastic energy of :mod:`physavatar.sim.energies` is linear in its stiffness and the inertia
and gravity terms are linear in ρ, so the motion only depends on κs/ρ and κb/ρ once the contact
and damping forces scale with mass (docs/simulation.md, "What is identifiable").

The PhysAvatar/Codim-IPC parameterisation is a base fabric (E = 0.076 MPa, ν = 0.071,
thickness 0.328 mm) scaled by multipliers in [0.1, 8]; :meth:`Material.from_codim_ipc` maps it.
:meth:`Material.from_arcsim` fits the linear isotropic model to the measured fabrics of Wang et
al. 2011 (ARCSim json: density, stretching and bending tables).
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np

from ..errors import PhysavatarError

# Base fabric of the official PhysAvatar Codim-IPC setup (docs/simulation.md).
CODIM_BASE_YOUNG = 0.076e6  # Pa
CODIM_BASE_POISSON = 0.071
CODIM_BASE_THICKNESS = 0.328e-3  # m
REST_SHAPES = ("template", "equilibrium")  # Material.rest_shape
FIT_REST_SHAPE = "equilibrium"  # what fit-physics (and reference-sims' draws) use by default, since session 28
FIT_REST_FRICTION = True  # fit-physics --rest-friction (Material.rest_friction): the default since session 36


@dataclasses.dataclass(frozen=True)
class Material:
    """A homogeneous cloth material (SI units; see module docstring).

    Attributes:
        density: ρ [kg/m²], area density.
        stretch_stiffness: κs [N/m], membrane Young's modulus × thickness.
        bend_stiffness: κb [N·m], flexural rigidity D of the shell.
        poisson: ν [-], membrane Poisson ratio, in [0, 0.5).
        name: free text.
        integrator: the time integrator the material was fitted with ("euler" or "bdf2";
            ``fit-physics`` records the one it selected). A fitted material is the best one for
            the simulation model it was fitted in, so :func:`simulate` (and everything built on
            it: ``simulate``, ``animate``) uses this integrator unless its settings are given.
        bdf2_blend: γ ∈ [0, 1], with integrator "bdf2": the weight of the step's history
            (solver ``step_base``): 1 is BDF2, 0 implicit Euler, in between a first-order blend
            whose numerical damping lies between theirs. ``fit-physics`` fits it with the
            stiffnesses; 1 for presets and older files.
        contact_offset: the cloth's contact thickness [m]: the simulations keep the cloth at
            least this far from the body (ipctk's minimum distance d_min, Codim-IPC's thickness
            ξ: the barrier acts on d² − d_min² within (2 d_min + d̂) d̂; SimSettings.dmin). Like
            the integrator it is part of the simulation model the material was fitted in:
            ``fit-physics`` estimates it from the garment's distance to the body where it rests
            on it (sim.offset.estimate_contact_offset) and records it, and every simulation of
            the material uses it unless its settings give a ``dmin``. 0 for presets and older
            files (no thickness).
        rest_shape: the garment's stress-free shape in every simulation of the material:
            "template" (the garment as placed, i.e. the captured first frame, loaded by gravity;
            presets and older files) or "equilibrium" (the rest shape whose static equilibrium on
            the body is that frame: sim.rest.equilibrium_rest, computed for this material by
            ``garment_sim.simulate_on_body`` and so by ``animate``, ``evaluate`` and the tracker's
            physics prediction). ``fit-physics --rest-shape equilibrium`` fits in that model and
            records it. A garment with a designed rest shape (a sewing pattern) keeps that one.
        rest_friction: with rest_shape "equilibrium": the equilibrium holds the garment with static
            friction against the body (the simulations' coefficient, anchored at the start:
            sim.rest.StaticFriction, session 36) instead of frictionless. ``fit-physics`` fits in
            that model and records it by default (``--no-rest-friction``: not); False (omitted)
            for presets and older files.
    """

    density: float = 0.131
    stretch_stiffness: float = CODIM_BASE_YOUNG * CODIM_BASE_THICKNESS
    bend_stiffness: float = (
        CODIM_BASE_YOUNG * CODIM_BASE_THICKNESS**3 / (12.0 * (1.0 - CODIM_BASE_POISSON**2))
    )
    poisson: float = CODIM_BASE_POISSON
    name: str = "codim-ipc-base"
    integrator: str = "euler"
    bdf2_blend: float = 1.0
    contact_offset: float = 0.0
    rest_shape: str = "template"
    rest_friction: bool = False

    UNITS = {
        "density": "kg/m^2",
        "stretch_stiffness": "N/m",
        "bend_stiffness": "N*m",
        "poisson": "1",
        "bdf2_blend": "1",
        "contact_offset": "m",
    }

    def __post_init__(self):
        for key in ("density", "stretch_stiffness", "bend_stiffness"):
            value = getattr(self, key)
            if not (np.isfinite(value) and value > 0):
                raise PhysavatarError(None, f"material {key} must be a positive number, got {value}")
        if not (0.0 <= self.poisson < 0.5):
            raise PhysavatarError(None, f"material poisson must be in [0, 0.5), got {self.poisson}")
        if self.integrator not in ("euler", "bdf2"):
            raise PhysavatarError(None, f"material integrator must be 'euler' or 'bdf2', got {self.integrator!r}")
        if not (np.isfinite(self.bdf2_blend) and 0.0 <= self.bdf2_blend <= 1.0):
            raise PhysavatarError(None, f"material bdf2_blend must be in [0, 1], got {self.bdf2_blend}")
        if not (np.isfinite(self.contact_offset) and 0.0 <= self.contact_offset < 0.05):
            raise PhysavatarError(None, f"material contact_offset must be in [0, 0.05) m, got {self.contact_offset}")
        if self.rest_shape not in REST_SHAPES:
            raise PhysavatarError(None, f"material rest_shape must be 'template' or 'equilibrium', got {self.rest_shape!r}")

    # -- derived quantities ------------------------------------------------------------------

    @property
    def stretch_ratio(self) -> float:
        """κs/ρ [m²/s²]: the membrane parameter video can identify."""
        return self.stretch_stiffness / self.density

    @property
    def bend_ratio(self) -> float:
        """κb/ρ [m³/s²]: the bending parameter video can identify."""
        return self.bend_stiffness / self.density

    def scaled(self, factor: float) -> "Material":
        """ρ, κs and κb all multiplied by ``factor`` (same ratios, same motion)."""
        return dataclasses.replace(
            self,
            density=self.density * factor,
            stretch_stiffness=self.stretch_stiffness * factor,
            bend_stiffness=self.bend_stiffness * factor,
        )

    # -- conversions -------------------------------------------------------------------------

    @classmethod
    def from_codim_ipc(
        cls,
        density_kg_m3: float = 400.0,
        stretch_mult: float = 1.0,
        bend_mult: float = 1.0,
        young: float = CODIM_BASE_YOUNG,
        poisson: float = CODIM_BASE_POISSON,
        thickness: float = CODIM_BASE_THICKNESS,
    ) -> "Material":
        """The PhysAvatar parameterisation: volume density [kg/m³] and stiffness multipliers.

        ρ = density × thickness; κs = E·t × stretch_mult; Codim-IPC's hinge coefficient is
        E t³ / (24 (1 − ν²)) × bend_mult, which is half the plate rigidity D = E t³/(12(1 − ν²));
        our hinge energy is normalised so that κb = D (docs/simulation.md), so
        κb = E t³/(12(1 − ν²)) × bend_mult.
        """
        return cls(
            density=density_kg_m3 * thickness,
            stretch_stiffness=young * thickness * stretch_mult,
            bend_stiffness=young * thickness**3 / (12.0 * (1.0 - poisson**2)) * bend_mult,
            poisson=poisson,
            name=f"codim-ipc(rho={density_kg_m3:g},ks×{stretch_mult:g},kb×{bend_mult:g})",
        )

    @classmethod
    def from_arcsim(cls, path: str | Path, poisson: float | None = None) -> "Material":
        """Fit the linear isotropic model to one ARCSim material file (Wang et al. 2011).

        ARCSim's ``stretching`` holds 6 samples of the 2D elasticity tensor (C11, C12, C22, C33)
        [N/m] at increasing strain; the first sample is the small-strain one. For an isotropic
        plane-stress membrane C11 = C22 = κs/(1−ν²), C12 = ν κs/(1−ν²), C33 = κs/(2(1+ν)). We
        take κs, ν from the small-strain sample by least squares on (C11, C22, C12, C33)
        (closed form below) unless ``poisson`` is given. ``bending`` holds 3 directions × 5
        curvature samples [N·m]; the fitted κb is the mean over directions of the smallest-
        curvature sample (the linear, small-angle regime that the hinge model describes).
        """
        path = Path(path)
        try:
            data = json.loads(path.read_text())
            rho = float(data["density"])
            stretch = np.asarray(data["stretching"], dtype=float)
            bend = np.asarray(data["bending"], dtype=float)
        except (OSError, ValueError, KeyError, TypeError) as err:
            raise PhysavatarError(path, f"not an ARCSim material file ({err})") from err
        if stretch.ndim != 2 or stretch.shape[1] != 4 or bend.ndim != 2:
            raise PhysavatarError(path, "stretching must be [k, 4] and bending [d, s]")
        c11, c12, c22, c33 = stretch[0]
        ks, nu = fit_isotropic_membrane(c11, c12, c22, c33, poisson)
        kb = float(np.mean(bend[:, 0]))
        return cls(density=rho, stretch_stiffness=ks, bend_stiffness=kb, poisson=nu, name=path.stem)

    def to_dict(self) -> dict:
        out = dataclasses.asdict(self)
        if out["rest_shape"] == "template":  # the model of every file before session 27: keys unchanged
            del out["rest_shape"]
        if not out["rest_friction"]:  # (files before session 36: keys unchanged)
            del out["rest_friction"]
        out["units"] = dict(self.UNITS)
        return out

    @classmethod
    def from_dict(cls, data: dict) -> "Material":
        fields = {f.name for f in dataclasses.fields(cls)}
        unknown = set(data) - fields - {"units"}
        if unknown:
            raise PhysavatarError(None, f"unknown material keys {sorted(unknown)}")
        return cls(**{k: v for k, v in data.items() if k in fields})

    def save(self, path: str | Path) -> None:
        from ..files import write_json_atomic

        write_json_atomic(path, self.to_dict())

    @classmethod
    def load(cls, path: str | Path) -> "Material":
        """A material.json: the simulator's own format, or fit-physics' (``{"material": {...}, ...}``)."""
        path = Path(path)
        try:
            data = json.loads(path.read_text())
        except (OSError, ValueError) as err:
            raise PhysavatarError(path, f"cannot read material json ({err})") from err
        if isinstance(data, dict) and isinstance(data.get("material"), dict):
            data = data["material"]  # fit-physics' material.json: {"material": {...}, "ratios": ..., ...}
        if not isinstance(data, dict):
            raise PhysavatarError(path, "not a material (expected a JSON object)")
        try:
            return cls.from_dict(data)
        except (PhysavatarError, TypeError, ValueError) as err:
            raise PhysavatarError(path, f"not a material ({err})") from None


def fit_isotropic_membrane(c11, c12, c22, c33, poisson=None) -> tuple[float, float]:
    """Least-squares (κs, ν) of an isotropic plane-stress membrane to an orthotropic tensor.

    With a = κs/(1−ν²): C11 ≈ a, C22 ≈ a, C12 ≈ ν a and C33 ≈ (1−ν) a / 2 (= κs/(2(1+ν))).
    For fixed ν the problem is linear in a: a = (C11 + C22 + ν C12 + (1−ν)/2 C33) /
    (2 + ν² + (1−ν)²/4); ν is then chosen on a fine grid in [0, 0.49] (the fit is one-
    dimensional and smooth, so a grid is exact enough and never fails). ν is capped at 0.45:
    near 0.5 the plane-stress membrane locks and Newton converges slowly. Returns (κs, ν).
    """
    target = np.array([c11, c22, c12, c33], dtype=float)
    grid = np.array([poisson], dtype=float) if poisson is not None else np.linspace(0.0, 0.45, 451)
    basis = np.stack([np.ones_like(grid), np.ones_like(grid), grid, 0.5 * (1.0 - grid)], axis=1)
    a = basis @ target / np.sum(basis**2, axis=1)
    residual = np.sum((basis * a[:, None] - target) ** 2, axis=1)
    best = int(np.argmin(residual))
    nu = float(grid[best])
    return float(a[best] * (1.0 - nu**2)), nu




# Presets: Material.from_arcsim fitted to three fabrics of Wang et al. 2011
# (/work/shared/data/materials, docs/simulation.md "Presets"); the numbers are frozen here so the
# package does not need the data folder, and tests/test_sim_material.py re-fits them.
PRESET_SOURCES = {
    "silk": "tango-red-jet-set",  # 100% polyester lining: lightest fabric, soft in bending
    "cotton": "gray-interlock",  # 60/40 cotton t-shirt knit
    "denim": "11oz-black-denim",  # 99% cotton jeans: heaviest, stiffest in stretch and bending
}
PRESETS: dict[str, Material] = {
    "silk": Material(
        density=0.113, stretch_stiffness=85.0306, bend_stiffness=1.88637e-05, poisson=0.45,
        name="silk",
    ),
    "cotton": Material(
        density=0.187, stretch_stiffness=30.8894, bend_stiffness=2.07364e-05, poisson=0.0,
        name="cotton",
    ),
    "denim": Material(
        density=0.324, stretch_stiffness=547.143, bend_stiffness=7.81775e-05, poisson=0.177,
        name="denim",
    ),
}


def preset(name: str) -> Material:
    """One of the named materials: ``"silk"`` (light), ``"cotton"`` (medium), ``"denim"`` (stiff)."""
    try:
        return PRESETS[name]
    except KeyError:
        raise PhysavatarError(None, f"unknown material preset {name!r}; choose from {sorted(PRESETS)}")
