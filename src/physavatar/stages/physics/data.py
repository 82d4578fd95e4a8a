"""What material estimation fits to (:class:`PhysicsData`), read from a folder, and its start state.

:func:`load_physics_data` reads a tracked folder, a capture's ground truth or a garment sequence;
:func:`clear_start` makes the window's first frame a state the simulator can start from.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np

from ...capture import template_rest
from ...data.garment_sequence import FILE as GARMENT_SEQUENCE
from ...data.garment_sequence import GarmentSequence
from ...data.tracked import FILE as TRACKED
from ...data.tracked import TrackedSequence
from ...errors import PhysavatarError
from ...files import load_npz, read_json, read_ply
from ...geometry import count_intersections, submesh
from .parameters import PAPER_WINDOW


@dataclasses.dataclass(frozen=True)
class PhysicsData:
    """What material estimation fits to.

    Attributes:
        reference: [T, N, 3] tracked garment vertices (frame 0 is the initial state, at rest).
        faces: [F, 3] garment triangles.
        boundary: [K] Dirichlet vertex ids (driven by ``boundary_targets``).
        collider: [T, Nb, 3] body vertices per frame, or None (no body).
        collider_faces: [Fb, 3] body triangles, or None.
        fps: frames per second of ``reference``.
        rest: [N, 3] the garment's stress-free shape (default ``reference[0]``).
        boundary_targets: [T, K, 3] boundary positions per frame (default: their tracked
            positions ``reference[:, boundary]``; an attachment to the body also works).
        targets_tracked: the boundary targets are the tracked positions (set when they were
            defaulted); :meth:`with_noise` then perturbs them as tracking noise would.
        initial: [N, 3] the state the simulation starts from, at rest (default: the reference
            frame 0, Algorithm 1). A known clean start (the template at rest) avoids feeding
            tracking noise into the first step as strain and near-contacts.
    """

    reference: np.ndarray
    faces: np.ndarray
    boundary: np.ndarray
    collider: np.ndarray | None = None
    collider_faces: np.ndarray | None = None
    fps: float = 25.0
    rest: np.ndarray | None = None
    boundary_targets: np.ndarray | None = None
    targets_tracked: bool = False
    initial: np.ndarray | None = None

    def __post_init__(self):
        ref = np.asarray(self.reference, dtype=np.float64)
        if ref.ndim != 3 or ref.shape[2] != 3 or len(ref) < 2:
            raise PhysavatarError(None, f"reference must be [T >= 2, N, 3], got {ref.shape}")
        if not np.all(np.isfinite(ref)):
            raise PhysavatarError(None, "reference vertices contain non-finite values")
        object.__setattr__(self, "reference", ref)
        object.__setattr__(self, "faces", np.asarray(self.faces, dtype=np.int64).reshape(-1, 3))
        b = np.unique(np.asarray(self.boundary, dtype=np.int64).ravel())
        object.__setattr__(self, "boundary", b)
        if self.rest is None:
            object.__setattr__(self, "rest", ref[0].copy())
        if self.boundary_targets is None:
            object.__setattr__(self, "boundary_targets", ref[:, b])
            object.__setattr__(self, "targets_tracked", True)
        if self.collider is not None:
            c = np.asarray(self.collider, dtype=np.float64)
            if c.ndim != 3 or len(c) != len(ref):
                raise PhysavatarError(None, f"collider must be [T={len(ref)}, Nb, 3], got {c.shape}")
            object.__setattr__(self, "collider", c)
        if not self.fps > 0:
            raise PhysavatarError(None, f"fps must be positive, got {self.fps}")

    @property
    def frames(self) -> int:
        return len(self.reference)

    def window(self, start: int = 0, length: int = PAPER_WINDOW) -> PhysicsData:
        """Frames [start, start + length) (the paper fits 24 frames, App. A.3.1)."""
        stop = min(self.frames, start + max(2, length))
        sl = slice(start, stop)
        return dataclasses.replace(
            self, reference=self.reference[sl],
            collider=None if self.collider is None else self.collider[sl],
            boundary_targets=self.boundary_targets[sl],
        )

    def with_noise(self, sigma_m: float, seed: int = 0) -> PhysicsData:
        """Gaussian noise of std ``sigma_m`` [m] per coordinate on the reference (benchmarks).

        The boundary targets (the simulation's input) stay clean unless they are the tracked
        positions (``targets_tracked``), in which case they carry the same noise.
        """
        if sigma_m <= 0:
            return self
        rng = np.random.default_rng(seed)
        ref = self.reference + rng.normal(0.0, sigma_m, self.reference.shape)
        return dataclasses.replace(
            self, reference=ref,
            boundary_targets=ref[:, self.boundary] if self.targets_tracked else self.boundary_targets,
        )


# -- the start state ------------------------------------------------------------------------------

# [m] a start vertex closer than this to the body is pushed out to START_CLEARANCE (the barrier
# is infinite at contact and stiff far inside d̂; another simulator's cloth may lie on the skin)
START_MIN_GAP = 2e-4
START_CLEARANCE = 1e-3  # = the fits' d̂


def clear_start(data: PhysicsData, source=None, frame: int = 0,
                sequence: PhysicsData | None = None) -> tuple[PhysicsData, dict]:
    """``data`` with an initial state the simulator can start from, and what was done to it.

    The simulation of a window starts from ``data.initial`` (default the reference frame 0) and
    IPC needs that state free of garment–body intersections, at a positive distance (its CCD
    assumes it; from a crossing start the solver runs but its steps are not valid, and the fit
    would follow a non-converged simulation without a word). Tracked garments and other
    simulators' output need not be: a simulator that only keeps the cloth's *vertices* out of the
    body lets limbs pass through the faces between them (docs/physics.md, "The start state").

    A start closer than :data:`START_MIN_GAP` or crossing the body is pushed out along the body
    normal to :data:`START_CLEARANCE` (garment.push_clear: push_out, then the crossings it cannot
    see; the boundary vertices stay at their targets). When it still crosses, this raises a :class:`PhysavatarError` naming ``source``, the
    ``frame`` (``data``'s first frame in ``sequence``) and the crossing pairs, with the frames of
    ``sequence`` (default ``data``, numbered from ``frame``) that are free of crossings, for
    ``--start``. Returns (data with ``initial`` set, info dict for material.json).
    """
    # garment designs load the body model: imported on use
    from ...garment.garment import body_clearance, push_clear

    x0 = np.asarray(data.reference[0] if data.initial is None else data.initial, dtype=np.float64)
    info = {"frame": int(frame), "crossing_pairs": 0, "min_gap_mm": None, "pushed_vertices": 0, "max_push_mm": 0.0}
    if data.collider is None or data.collider_faces is None:
        return dataclasses.replace(data, initial=x0), info
    body, bfaces = data.collider[0], data.collider_faces
    crossing = count_intersections(x0, data.faces, body, bfaces, fixed=data.boundary)
    gap = body_clearance(x0, data.faces, body, bfaces)
    info.update(crossing_pairs=int(crossing), min_gap_mm=1e3 * gap)
    if crossing == 0 and gap >= START_MIN_GAP:
        return dataclasses.replace(data, initial=x0), info
    moved, left = push_clear(x0, data.faces, body, bfaces, START_CLEARANCE, fixed=data.boundary)
    if left:
        seq, first = (sequence, 0) if sequence is not None else (data, frame)
        clean = [first + f for f in range(min(seq.frames, 200))
                 if not count_intersections(seq.reference[f], seq.faces, seq.collider[f], bfaces, fixed=seq.boundary)]
        where = (f"frames free of crossings: {clean[:12]}" + (" ..." if len(clean) > 12 else "")
                 if clean else "no frame is free of crossings")
        raise PhysavatarError(source, f"the garment crosses the body at frame {frame} ({crossing} intersecting "
                                      f"triangle pairs, {left} after pushing it out): the simulation needs an "
                                      f"intersection-free start; {where}")
    step = np.linalg.norm(moved - x0, axis=1)
    info.update(pushed_vertices=int(np.count_nonzero(step > 0)), max_push_mm=1e3 * float(step.max()),
                min_gap_after_mm=1e3 * body_clearance(moved, data.faces, body, bfaces))
    return dataclasses.replace(data, initial=moved), info



def load_physics_data(folder: str | Path) -> PhysicsData:
    """A tracked folder (``tracked.npz``: vertices [T, V, 3], faces, labels) or a capture with
    ``ground_truth/meshes.npz``; the boundary flags come from the capture template (the
    tracked folder's ``boundary`` array, or its capture's ``template/mesh.ply``). A folder with
    ``garment_sequence.npz`` (``physavatar simulate``'s output), or an .npz without ``labels``
    given by name, is a garment sequence (:func:`load_garment_sequence`).

    The garment is every vertex with label ≥ 1 (the first garment when there are several);
    the body (label 0) is the collider, and garment faces are those with all three corners on
    the garment. The garment's rest shape is the template's (frame-1 mesh); a ``tracked.npz``
    with no template to be found (another tool's sequence) takes its frame 0 as the rest shape
    and its own ``boundary`` flags, or none. A garment without boundary (Dirichlet) vertices
    is simulated as held by contact and friction alone.
    """
    folder = Path(folder)
    z = None  # the tracked arrays, when a file given by name was read already
    if folder.is_file() and folder.suffix == ".npz":
        z = load_npz(folder)
        if "labels" not in z:
            return load_garment_sequence(folder, z)
        tracked, folder = folder, folder.parent  # a tracked.npz-style file given by name
    elif not folder.is_dir():
        raise PhysavatarError(folder, "not a folder or .npz (expected a tracked folder, a capture or a garment sequence)")
    else:
        tracked = folder / TRACKED
        if not tracked.is_file() and not (folder / "ground_truth" / "meshes.npz").is_file() \
                and (folder / GARMENT_SEQUENCE).is_file():
            return load_garment_sequence(folder / GARMENT_SEQUENCE)
    if tracked.is_file():
        src = tracked
    else:
        src = folder / "ground_truth" / "meshes.npz"
        if not src.is_file():
            raise PhysavatarError(folder, "none of tracked.npz, ground_truth/meshes.npz, garment_sequence.npz found")
    # a capture's ground-truth meshes have the tracked format (its boundary flags are the template's)
    seq = TrackedSequence.from_arrays(load_npz(src) if z is None else z, src,
                                      require=("vertices", "faces", "labels"), min_frames=2)
    boundary = seq.boundary if src == tracked else None
    rest = None
    fps = 25.0 if seq.fps is None else seq.fps
    template_dir = folder
    verts = np.asarray(seq.vertices, dtype=np.float64)
    faces, labels = seq.faces, seq.labels
    ply = None
    if boundary is None or rest is None:
        ply = template_dir / "template" / "mesh.ply"
        if not ply.is_file() and (template_dir / "capture").is_dir():
            ply = template_dir / "capture" / "template" / "mesh.ply"
        if not ply.is_file() and (template_dir / "config.json").is_file():
            # a tracking folder records the capture it tracked
            cap = read_json(template_dir / "config.json").get("capture")
            if cap:
                ply = Path(cap) / "template" / "mesh.ply"
        if not ply.is_file() and src.name == "tracked.npz":
            rest = verts[0]  # a sequence on its own: its first frame is the template
            ply = None
        elif not ply.is_file():
            raise PhysavatarError(template_dir, "no template/mesh.ply with the garment's rest shape and boundary flags")
    if ply is not None and (boundary is None or rest is None):
        try:
            mesh = read_ply(ply)
        except PhysavatarError:
            raise
        except Exception as e:  # a malformed PLY of any kind
            raise PhysavatarError(ply, f"cannot read template ({e})") from None
        if len(mesh.vertices) != len(labels):
            raise PhysavatarError(ply, f"template has {len(mesh.vertices)} vertices, {src.name} has {len(labels)}")
        if boundary is None:
            boundary = np.asarray(mesh.vertex_data.get("boundary", np.zeros(len(labels)))).astype(bool)
        given = template_rest(mesh, np.asarray(labels), ply)  # the template's own rest shape, if it has one
        rest = mesh.vertices if given is None else given
    garment_ids = sorted(set(labels.tolist()) - {0})
    if not garment_ids:
        raise PhysavatarError(src, "no garment vertices (labels >= 1)")
    gidx, gfaces = submesh(faces, labels == garment_ids[0])
    bidx, bfaces = submesh(faces, labels == 0)
    gboundary = np.flatnonzero(boundary[gidx]) if boundary is not None else np.zeros(0, np.int64)
    return PhysicsData(
        reference=verts[:, gidx], faces=gfaces, boundary=gboundary,
        collider=verts[:, bidx] if len(bidx) else None, collider_faces=bfaces if len(bidx) else None,
        fps=fps, rest=np.asarray(rest, np.float64)[gidx],
    )


def load_garment_sequence(path: str | Path, z=None) -> PhysicsData:
    """A garment simulated on a moving body, as ``physavatar simulate`` writes it
    (``garment_sequence.npz``) and as any cloth simulator can: ``vertices`` [T, N, 3] (the garment),
    ``faces`` [F, 3]; optional ``boundary`` (per-vertex flags [N] or vertex ids [K]: the attached
    vertices, none = held by contact alone), ``body_vertices`` [T, Nb, 3] with ``body_faces``
    (the collider), ``fps`` (25) and ``rest_vertices`` [N, 3] (the stress-free shape; default
    frame 0)."""
    path = Path(path)
    seq = GarmentSequence.from_arrays(load_npz(path) if z is None else z, path)
    return PhysicsData(reference=seq.vertices, faces=seq.faces, boundary=seq.boundary, collider=seq.body_vertices,
                       collider_faces=seq.body_faces, fps=seq.fps, rest=seq.rest_vertices)
