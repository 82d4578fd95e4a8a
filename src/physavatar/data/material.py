"""Materials as the stages take and write them.

:func:`resolve_material` is the one reading of "a preset name or a material .json" (``simulate
--material``, ``fit-physics --init``, ``build-avatar --material``).

:class:`FittedMaterial` is fit-physics' ``material.json``: the simulator's
:class:`~physavatar.sim.material.Material` (``"material"``) with what the fit found out about it::

    material          the Material (density, stiffnesses, poisson, integrator, bdf2_blend)
    ratios            stretch_ratio / bend_ratio: value, unit, symbol, interval95 [lo, hi] or null
    integrator        the time integrator it was fitted in (= material.integrator)
    start_state       what was done to the start frame (clear_start), or null
    ...               loss, rms_mm, iterations, settings, model_selection, proxy (FitResult.to_json)

:meth:`Material.load` reads both this file and the simulator's own format, so everything that
only simulates with a material (``simulate``, ``build-avatar``) keeps using it.
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

from ..errors import PhysavatarError
from ..files import write_json_atomic
from ..sim.material import PRESETS, Material

FILE = "material.json"


def material_file(path: str | Path) -> Path:
    """A fit-physics output folder's ``material.json``, or ``path`` itself when it is a file."""
    path = Path(path)
    return path / FILE if path.is_dir() else path


def resolve_material(spec: str | Path | Material, option: str | None = None) -> Material:
    """``spec`` as a Material: a Material as it is, a preset name (silk, cotton, denim), or a
    material .json file (the simulator's format or fit-physics'). With ``option`` (a command-line
    option's name), a string that is neither a preset nor a ``.json`` path is refused naming it."""
    if isinstance(spec, Material):
        return spec
    if isinstance(spec, str) and spec in PRESETS:
        return PRESETS[spec]
    if option is not None and not str(spec).endswith(".json"):
        raise PhysavatarError(None, f"option {option}: {spec!r} is not one of {', '.join(PRESETS)} or a .json file")
    return Material.load(spec)


@dataclasses.dataclass
class FittedMaterial:
    """fit-physics' material.json (module docstring): ``material`` and the whole ``record`` as
    written (its ``"material"`` entry is ``material.to_dict()``)."""

    material: Material
    record: dict
    path: Path | None = dataclasses.field(default=None, compare=False)

    @classmethod
    def from_json(cls, data: dict, path: str | Path | None = None) -> "FittedMaterial":
        path = None if path is None else Path(path)
        if not isinstance(data, dict) or not isinstance(data.get("material"), dict):
            raise PhysavatarError(path, "not a fitted material (expected fit-physics' material.json with a "
                                        "'material' object)")
        try:
            material = Material.from_dict(data["material"])
        except (PhysavatarError, TypeError, ValueError) as err:
            raise PhysavatarError(path, f"not a material ({err})") from None
        fitted = cls(material, dict(data), path)
        fitted.validate()
        return fitted

    @classmethod
    def load(cls, path: str | Path) -> "FittedMaterial":
        """``path``: a fit-physics output folder (its ``material.json``) or the file."""
        path = material_file(path)
        try:
            data = json.loads(path.read_text())
        except (OSError, ValueError) as err:
            raise PhysavatarError(path, f"cannot read material json ({err})") from err
        return cls.from_json(data, path)

    @property
    def intervals(self) -> dict:
        """95 % intervals of the identifiable ratios: {"stretch_ratio": [lo, hi] or None, ...}."""
        return {k: v.get("interval95") for k, v in (self.record.get("ratios") or {}).items()}

    @property
    def integrator(self) -> str:
        return self.material.integrator

    @property
    def start_state(self) -> dict | None:
        return self.record.get("start_state")

    def validate(self) -> None:
        """The intervals are [lo <= hi] or null and the recorded integrator is the material's;
        raises :class:`PhysavatarError` naming :attr:`path`."""
        ratios = self.record.get("ratios") or {}
        if not isinstance(ratios, dict) or not all(isinstance(v, dict) for v in ratios.values()):
            raise PhysavatarError(self.path, "ratios must map each ratio to {value, unit, symbol, interval95}")
        for key, iv in self.intervals.items():
            if iv is not None and not (isinstance(iv, (list, tuple)) and len(iv) == 2
                                       and all(isinstance(x, (int, float)) for x in iv) and iv[0] <= iv[1]):
                raise PhysavatarError(self.path, f"ratios.{key}.interval95 must be [low, high] or null, got {iv!r}")
        recorded = self.record.get("integrator", self.material.integrator)
        if recorded != self.material.integrator:
            raise PhysavatarError(self.path, f"integrator {recorded!r} differs from the material's "
                                             f"{self.material.integrator!r}")
        if self.start_state is not None and not isinstance(self.start_state, dict):
            raise PhysavatarError(self.path, "start_state must be an object or null")

    def to_json(self) -> dict:
        return {**self.record, "material": self.material.to_dict()}

    def save(self, path: str | Path) -> Path:
        path = Path(path)
        self.validate()
        write_json_atomic(path, self.to_json())
        return path
