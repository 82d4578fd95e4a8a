"""``physavatar prepare``'s settings: one group per step (masks, mesh, segmentation, boundary).

The body fit's settings (``BodyFitConfig``) belong to :mod:`.body_fit`.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from ..base import option, setting
from .body_fit import BodyFitConfig


def _positive(v):
    return None if v > 0 else "must be positive"


def _fraction(v):
    return None if 0 < v < 1 else "must be between 0 and 1"


def _path_or_none(text: str) -> Path | None:
    return Path(text) if text else None


@dataclass(frozen=True)
class MaskConfig:
    """Foreground masks when the capture has none (stages/prepare/masks.py)."""

    method: str = option("auto", "how masks are computed: difference (background differencing), mediapipe (its person "
                         "segmentation, the keypoints extra), auto (difference with a background plate, else "
                         "mediapipe when installed, else difference)", flag="--mask-method",
                         choices=("auto", "difference", "mediapipe"))
    segmentation_threshold: float = setting(0.5)  # MediaPipe's person probability counted as foreground
    threshold: float = option(0.0, "colour difference to the background counted as foreground (0..1; 0 = chosen per "
                              "camera: Otsu's method, or 3x the border colours' scatter)", flag="--mask-threshold",
                              check=lambda v: None if 0 <= v < 1 else "must be in [0, 1)")
    min_threshold: float = setting(0.04)  # Otsu's choice is never below this (noise in a static background)
    open_px: int = setting(0)  # morphological opening radius (removes speckle; 0: none)
    close_px: int = setting(1)  # closing radius (fills cracks between body parts)
    min_area: float = setting(0.002)  # connected regions smaller than this share of the image are dropped
    refine: int = setting(2)  # background re-estimations without the frames' foreground
    border_share: float = setting(0.6)  # median image share explained by border colours to use them too
    border_max_threshold: float = setting(0.15)  # a border this varied is no backdrop (a room): not used
    max_clutter: float = setting(0.15)  # differenced masks with more foreground outside the largest region: warned
    max_foreground: float = setting(0.5)  # or more of the image foreground: warned


@dataclass(frozen=True)
class MeshConfig:
    """The first-frame mesh: visual hull, manifold repair, isotropic remeshing (mesh.py)."""

    voxel: float = option(0.0, "visual-hull voxel size [m] (0: a pixel's footprint, at least a third of the edge "
                          "length, 4 mm .. 2 cm)",
                          flag="--voxel", check=lambda v: None if v >= 0 else "must be at least 0")
    edge_length: float = option(0.02, "target edge length of the remeshed surface [m]", flag="--edge-length",
                                check=_positive)
    remesh_iterations: int = setting(10)
    view_share: float = setting(1.0)  # share of the cameras that must see a voxel (1: their common volume)
    # thin sheets (a strap standing off the skin) kept in the hull: up to sheet_views cameras may
    # hold a voxel below half where it lies on a thin line of their mask (narrower than sheet_px
    # pixels, covering sheet_level or more; 0: the plain hull; docs/prepare.md, session 37)
    sheet_views: int = setting(0)
    sheet_level: float = setting(0.15)
    sheet_px: int = setting(3)
    sheet_reach: float = setting(0.0)  # the thin line counts within this many voxels of a voxel's centre
    smooth: int = setting(3)  # Taubin smoothing passes on the marching-cubes surface (voxel staircase)
    clothing_footprint: float = setting(0.01)  # [m] a hull from coarser pixels does not guide the body fit


@dataclass(frozen=True)
class RefineConfig:
    """The visual hull refined by photo-consistency and the fitted body (refine.py)."""

    photo: bool = option(True, "move the hull onto the most photo-consistent surface along its normals",
                         flag="--refine-photo/--no-refine-photo")
    body_prior: bool = option(True, "draw hull parts no camera sees onto the fitted body",
                              flag="--refine-body/--no-refine-body")
    search_in: float = setting(0.04)  # [m] how far inside the hull the surface is searched
    search_max: float = setting(0.08)  # [m] deeper where the fitted body is: down to it (+ body_slack), up to this
    body_slack: float = setting(0.01)  # [m] how far past the fitted body the search goes (the fit's error)
    search_out: float = setting(0.004)  # [m] and outside (the hull's own discretisation)
    step_px: float = setting(0.5)  # search step in pixel footprints
    patch: int = setting(5)  # patch of patch x patch samples on the tangent plane
    patch_px: float = setting(1.5)  # sample spacing in pixel footprints
    cameras: int = setting(4)  # the best-facing cameras of each vertex
    min_cos: float = setting(0.3)  # cameras seeing the surface more obliquely are not used
    min_contrast: float = setting(0.02)  # patches flatter than this (grey std, 0..1) carry no evidence
    min_score: float = setting(0.7)  # the best NCC must reach this
    min_peak: float = setting(0.15)  # and exceed the vertex's median NCC by this
    agree_rings: int = setting(2)  # a depth must agree with the median of its neighbours' within this many rings
    agree_px: float = setting(2.5)  # to within this many pixel footprints (0: no check)
    w_photo: float = setting(3.0)
    unseen_cos: float = setting(0.1)  # a vertex no camera sees (z-buffer) at a cosine above this is unseen
    w_body: float = setting(10.0)
    w_hull: float = setting(0.05)  # seen vertices without photo evidence keep to the hull this much
    w_offset: float = setting(3.0)  # seen vertices without evidence above their neighbours' height over the body (0: off)
    offset_tol: float = setting(5.0)  # by more than this many pixel footprints are drawn down to it
    offset_rings: float = setting(4.0)  # that height is the evidence's spread over about this many edges
    offset_support: float = setting(0.2)  # and is used where the evidence's spread indicator is this or more
    # unseen vertices drawn onto the body whose hull normal's up component is at most this (the
    # underside between a hem and the legs) are smoothed apart from the seen vertices amid photo
    # evidence (-2: not at all; docs/prepare.md, session 36)
    split_up: float = setting(0.0)
    body_margin: float = setting(0.0)  # [m] unseen parts land this far outside the body
    smoothness: float = setting(0.3)  # Laplacian weight of the displacement field
    chunk: int = setting(256)  # vertices per vectorised block


@dataclass(frozen=True)
class SegmentConfig:
    """Body / garment labels of the first-frame mesh (segment.py)."""

    labels: Path | None = option(None, "per-vertex labels instead of the automatic segmentation: a PLY with a "
                                 "'label' property (transferred by nearest point) or a .npy/.txt with one label "
                                 "per vertex of the capture's mesh", flag="--labels", parse=_path_or_none)
    margin: float = option(0.008, "vertices farther than this outside the fitted body are garment [m]",
                           flag="--garment-margin", check=_positive)
    softness: float = setting(0.004)  # [m] width of the distance term's transition
    refined_margin: float = setting(0.005)  # [m] the margin on a refined hull (refine.py), which has no slack
    refined_softness: float = setting(0.002)  # [m] and its transition
    refined_footprint: float = setting(1.0)  # and at least this many pixel footprints
    distance_cap: float = setting(3.0)  # the distance term's log-odds are capped at this
    bridge_normal: float = setting(-0.8)  # unseen vertices facing further down than this are body (hull bridges)
    colour_weight: float = setting(1.0)  # weight of the colour likelihood against the distance term
    under_weight: float = setting(1.0)  # weight of the cameras' agreement on the body under a vertex (bare skin)
    under_cap: float = setting(1.5)  # and its log-odds cap
    photo_weight: float = setting(1.0)  # weight of the photo-consistency evidence at each vertex (refine.py)
    photo_cap: float = setting(3.0)  # and its log-odds cap
    photo_rings: int = setting(1)  # evidence counts within this many mesh rings of a vertex
    under_occlusion: bool = setting(True)  # cameras seeing other garment in front of the body point are left out
    smoothness: float = option(1.5, "graph-cut smoothness between neighbouring vertices", flag="--segment-smoothness",
                               check=lambda v: None if v >= 0 else "must be at least 0")
    garments: int = option(1, "number of garments to separate by colour", flag="--garments",
                           check=lambda v: None if 1 <= v <= 15 else "must be 1..15")
    min_piece: float = setting(0.05)  # garment pieces smaller than this share of the garment are dropped
    strap_gap: float = setting(0.25)  # [m] a garment's local top joins higher garment across at most this (gaps.py; 0: off)
    strap_evidence: float = setting(0.0)  # a join's way costs length x (1 + this x P(body)) (gaps.py; 0: the shortest)
    strap_widen: int = setting(1)  # a join's band: the way and this many rings of vertices around it are garment


@dataclass(frozen=True)
class BoundaryConfig:
    """Where each garment stays on the body (boundary.py)."""

    file: Path | None = option(None, "boundary override: a PLY with a 'boundary' property or a .npy/.txt of "
                               "3D points; garment vertices within one edge length of them become boundary",
                               flag="--boundary", parse=_path_or_none)
    contact: float = option(0.02, "a garment vertex within this distance of the body in every frame is in "
                            "contact [m]", flag="--contact", check=_positive)
    top_band: float = setting(0.04)  # [m] contact regions must reach within this of a garment's highest contact
    frames: int = setting(12)  # frames sampled for the contact test
    min_region: int = setting(2)  # contact regions of fewer vertices are not holds
    grow: bool = setting(True)  # a kept hold grows over the contact vertices joined to it, within the band
    # [m] then along the garment (geodesic) over contact vertices by this much, past the band: the band is
    # in height, and where the garment drops steeply behind the crest (a strap down the back of the
    # shoulder) it stops short; a missing row of holds costs far more than an extra one. 0 (off): with
    # 0.02 the demo's held-out Chamfer fell 7-9 %, but `run`'s fit-physics refused the fitted-body
    # preparation (its proxy crossed the body at the start; docs/prepare.md, session 35)
    grow_along: float = setting(0.0)
    inside: float = setting(0.9)  # share of cameras whose mask must hold the skinned vertex in a sampled frame


@dataclass(frozen=True)
class PrepareConfig:
    """``physavatar prepare``: fill in what a capture lacks (docs/prepare.md)."""

    masks: MaskConfig = field(default_factory=MaskConfig)
    mesh: MeshConfig = field(default_factory=MeshConfig)
    refine: RefineConfig = field(default_factory=RefineConfig)
    body: BodyFitConfig = field(default_factory=BodyFitConfig)
    segment: SegmentConfig = field(default_factory=SegmentConfig)
    boundary: BoundaryConfig = field(default_factory=BoundaryConfig)
    calibrate: bool = option(True, "correct each camera's image offset from the person's keypoints when the masks' "
                             "hull agrees (only when the body and mesh are not given)",
                             flag="--calibrate/--no-calibrate")
    copy_images: bool = option(False, "copy the images instead of hard-linking them", flag="--copy-images")
    report: bool = option(True, "write the preparation report (report.md and pictures)", flag="--report/--no-report",
                          hash=False)
    seed: int = setting(0)
