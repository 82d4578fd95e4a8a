"""A simulation's frames written as they are finished, and where an interrupted run resumes.

``simulate`` and ``animate`` keep, inside their output folder while they run::

    frames/run.json     {"key": fingerprint of what is simulated and how, "frames": T}
    frames/NNNNNN.npz   x [N, 3] float64 (the garment at that simulated frame), report (JSON:
                        substeps, Newton iterations, contacts, lag; sim.simulate.frame_report)
    frames/state.npz    the sim.Checkpoint after the last frame written (positions,
                        velocities, the solver's state)

Every file is written atomically, frame file first, then the state. A run that finds a
``frames/`` folder with the same key resumes after the state's frame; with another key it
starts over. At the end the stage assembles its final file (garment_sequence.npz /
sequence.npz, atomically) from the frames and removes the folder.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np

from ..errors import PhysavatarError
from ..files import content_key, load_npz, read_json, save_npz_atomic, write_json_atomic
from ..sim.simulate import Checkpoint

FOLDER = "frames"


def fingerprint(*arrays, **meta) -> str:
    """A hex digest of arrays (dtype, shape and bytes) and JSON-able settings: the identity of
    a simulation run (two runs with equal fingerprints compute the same frames); files.content_key."""
    return content_key(*arrays, **meta)


def garment_run_key(part, bodies, body_faces, material, settings, fps: float, **meta) -> str:
    """The :func:`fingerprint` of simulating GarmentPart ``part`` on ``bodies`` [T, Nb, 3]
    (``body_faces``) with ``material`` and SimSettings ``settings``: everything of the part that
    garment_sim.simulate_on_body reads (start and rest shape, triangles, boundary, seams), the body
    motion and the settings that change results (:func:`run_settings`); ``meta``: the caller's
    other settings (substeps ...). ``simulate`` and ``animate`` resume by it (simulate's key as
    before session 27; animate's now also holds the rest shape and seams)."""
    return fingerprint(part.vertices, part.rest_shape, part.faces, part.boundary, bodies, body_faces,
                       *([] if part.seams is None else [part.seams]), material=material.to_dict(),
                       settings=run_settings(settings), fps=fps, **meta)


RESULT_NEUTRAL = ("ccd_threads", "candidate_threads")  # SimSettings fields that change no result (same bits)


def run_settings(settings) -> dict | None:
    """The SimSettings of a run as its fingerprint holds them: every field but the ones that
    change no result (``RESULT_NEUTRAL``: thread counts, bit-identical on any number), so a run
    resumes on another thread count; ``candidate_threads`` only as whether it is ≥ 1 (the barrier
    sets sorted: docs/simulation.md "Session 32")."""
    if settings is None:
        return None
    import dataclasses

    out = {k: v for k, v in dataclasses.asdict(settings).items() if k not in RESULT_NEUTRAL}
    if getattr(settings, "candidate_threads", 0) > 0:  # sorted barrier sets: other bits than 0's (any k ≥ 1 alike)
        out["canonical_contacts"] = True
    if not out.get("factor_thread", True):  # off (the default): the key of the code before session 37
        del out["factor_thread"]
    return out


class FrameStore:
    """``out/frames/`` of one run (module docstring). ``key``: :func:`fingerprint` of the run;
    ``total``: its frame count T (frame 0, the initial state, is not written)."""

    def __init__(self, out: str | Path, key: str, total: int):
        self.folder = Path(out) / FOLDER
        self.key, self.total = key, int(total)

    def _frame_path(self, f: int) -> Path:
        return self.folder / f"{f:06d}.npz"

    def resume(self) -> Checkpoint | None:
        """The checkpoint to continue from when the folder holds this run (same key, the state
        and every frame up to it readable); otherwise clear it, start the run's record, None."""
        ck = None
        try:
            run = read_json(self.folder / "run.json")
            if run.get("key") == self.key and int(run.get("frames", -1)) == self.total:
                ck = Checkpoint.load(self.folder / "state.npz")
                if not (0 < ck.frame < self.total and all(self._frame_path(f).is_file() for f in range(1, ck.frame + 1))):
                    ck = None
        except (PhysavatarError, KeyError, ValueError):
            ck = None
        if ck is None:
            self.remove()
            self.folder.mkdir(parents=True, exist_ok=True)
            write_json_atomic(self.folder / "run.json", {"key": self.key, "frames": self.total})
        return ck

    def write(self, checkpoint: Checkpoint, report: dict) -> None:
        """Frame ``checkpoint.frame``'s positions and report, then the state to resume from."""
        save_npz_atomic(self._frame_path(checkpoint.frame), x=checkpoint.x, report=np.asarray(json.dumps(report)))
        checkpoint.save(self.folder / "state.npz")

    def frame(self, f: int) -> tuple[np.ndarray, dict]:
        """(positions [N, 3] float64, report) of written frame ``f``."""
        z = load_npz(self._frame_path(f))
        return np.asarray(z["x"], np.float64), json.loads(str(z["report"]))

    def positions(self, x0: np.ndarray) -> tuple[np.ndarray, list[dict]]:
        """([T, N, 3] every frame, frame 0 = ``x0``; the reports of frames 1..T−1)."""
        X = np.empty((self.total,) + np.shape(x0))
        X[0] = x0
        reports = []
        for f in range(1, self.total):
            X[f], r = self.frame(f)
            reports.append(r)
        return X, reports

    def remove(self) -> None:
        if self.folder.exists():
            shutil.rmtree(self.folder)
