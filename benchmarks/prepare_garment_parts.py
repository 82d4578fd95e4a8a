"""Which property of the prepared garment makes its held-out Chamfer on the true body (issue 23, session 33).

    python benchmarks/prepare_garment_parts.py --original EXCERPT --prepared-true PREP_T --work W \
        [--only NAME,...] [--results benchmarks/results/prepare_garment_parts_s33.json]

``EXCERPT`` is the 12-frame excerpt (its template, body.npz, ground truth), ``PREP_T`` the same
prepared with the true body.npz given (`prepare_accuracy.py --given-body`, or `physavatar prepare`
of the excerpt without template/ and with its body.npz). Every variant is worn on the TRUE body
(the excerpt's body.npz: shape and frame-1 pose, which is the held-out motion's first pose, so no
warm-up) and animated with the TRUE material as `prepare_heldout_parts.py` does
(:func:`prepare_heldout_parts.heldout_cd`: `animate`, the garment Chamfer ×10³ of 10,000 points,
seed 0, against the held-out truth re-expressed on the variant's template by `carry_truth`). One
property changes at a time:

* the score: the original garment scored through `carry_truth` (as a prepared one is), and
  remeshed by gpytoolbox's `remesh_botsch` to 2-cm edges (the prepared hull's) with its boundary
  the remeshed vertices within 1.2 cm of a true one;
* the surface's error: the original garment moved along its normals by noise (mean |offset|
  2.5 mm, smoothed by 20 rounds of neighbour averaging, or 2 mm per vertex; seed 0; boundary
  kept), as the template and rest shape, or as the start only (the rest shape the original's);
  and 3 mm outward everywhere;
* the rest shape: the original's Taubin-smoothed (10 rounds, λ 0.5, μ −0.53, boundary fixed);
  the prepared one's too; the prepared one's bending rest angles flat (``--flat`` only: the
  simulator's ``Bending.rest_angle`` set to 0 inside this process);
* the region: the original garment without its hem band that the prepared garment misses (its
  vertices below z 0.35 m more than 1 cm from the prepared garment);
* the straps' width: the original garment with one strap narrowed to the prepared straps' necks;
* the holds: the original garment with the prepared boundary (its vertices within 2 cm of the
  prepared boundary points);
* the prepared garment's geometry: its vertices moved onto the true surface (closest point;
  halved where a triangle would lose 80 % of its area), start and rest, with its own boundary and
  with the true one (the moved vertices within 1.2 cm of a true boundary point).

Per variant also: the garment's mean drop (mm) at held-out frame 8 by height (the truth falls 13 cm
from its unloaded template in 8 frames and bounces on its straps; the drop's error is most of the
Chamfer), and for the templates the straps' cross-section (cm) at z 1.22-1.33 m (plane sections of
the garment, by side and front/back). Writes ``checks`` (reported figures, no target); W/NAME/result.json
caches each variant.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import json
import os
import sys
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
from _common import write_heldout_result
from prepare_heldout_parts import heldout_cd

DROP_BANDS = (0.29, 0.5, 0.8, 1.0, 1.2, 1.3, 1.42)  # [m] frame-0 heights of the drop's bands
STRAP_Z = (1.22, 1.26, 1.30, 1.33)  # [m] heights of the straps' sections


def _template(t, vertices=None, boundary=None, rest=None):
    from physavatar.capture import Template

    return Template(t.vertices if vertices is None else vertices, t.faces, t.labels,
                    t.boundary if boundary is None else boundary, t.face_uvs, rest)


def garment_normals(t) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(garment vertex ids, their faces in those ids, unit vertex normals)."""
    from physavatar.geometry import submesh
    from physavatar.geometry.mesh import vertex_normals

    ids, f = submesh(t.faces, t.labels > 0)
    return ids, f, vertex_normals(t.vertices[ids], f)


def normal_noise(t, amp_mm: float, smooth_rounds: int, seed: int = 0) -> np.ndarray:
    """[V, 3] ``t``'s vertices with its garment (boundary kept) moved along the normals by Gaussian
    noise averaged over neighbours ``smooth_rounds`` times (x ← (x + mean of neighbours) / 2) and
    scaled to a mean |offset| of ``amp_mm`` over the free vertices."""
    from physavatar.geometry.mesh import adjacency

    ids, f, n = garment_normals(t)
    x = np.random.default_rng(seed).standard_normal(len(ids))
    A = adjacency(f, len(ids))
    deg = np.asarray(A.sum(1)).ravel()
    for _ in range(smooth_rounds):
        x = 0.5 * x + 0.5 * (A @ x) / deg
    free = ~t.boundary[ids]
    x = np.where(free, x * amp_mm * 1e-3 / np.abs(x[free]).mean(), 0.0)
    V = t.vertices.copy()
    V[ids] += x[:, None] * n
    return V


def offset_out(t, mm: float) -> np.ndarray:
    """[V, 3] ``t``'s vertices with its garment (boundary kept) ``mm`` out along the normals."""
    ids, _, n = garment_normals(t)
    V = t.vertices.copy()
    V[ids] += np.where(t.boundary[ids], 0.0, mm * 1e-3)[:, None] * n
    return V


def taubin_rest(t, rounds: int = 10, lam: float = 0.5, mu: float = -0.53) -> np.ndarray:
    """[V, 3] ``t``'s vertices with its garment Taubin-smoothed (uniform weights, boundary fixed):
    trimesh's filter_taubin, ``rounds`` λ/μ pairs."""
    import scipy.sparse as sp
    import trimesh
    from trimesh.smoothing import filter_taubin

    from physavatar.geometry.mesh import adjacency

    ids, f, _ = garment_normals(t)
    m = trimesh.Trimesh(t.vertices[ids].copy(), f, process=False)
    # the neighbours' mean, pinned rows the identity (trimesh's own equal-weight operator takes each
    # open edge in one direction only: a strap's edge vertices would average one side)
    A = adjacency(f, len(ids)).astype(np.float64).tocsr()
    A.data[:] = 1.0
    pin = t.boundary[ids]
    L = sp.diags(np.where(pin, 0.0, 1.0 / np.asarray(A.sum(1)).ravel())) @ A + sp.diags(pin.astype(np.float64))
    filter_taubin(m, lamb=lam, nu=-mu, iterations=2 * rounds, laplacian_operator=L)  # a pass is λ or μ
    V = t.vertices.copy()
    V[ids] = m.vertices
    return V


def onto_truth(t, truth, keep_area: float = 0.2) -> np.ndarray:
    """[V, 3] ``t``'s garment vertices moved to the closest point of ``truth``'s garment surface
    (its boundary kept); a vertex of a triangle that would keep less than ``keep_area`` of its area
    moves half as far, repeated."""
    from physavatar.geometry.closest import MeshQuery

    ids, f, _ = garment_normals(t)
    X0 = t.vertices[ids]
    tf = truth.faces[(truth.labels[truth.faces] > 0).all(1)]
    _, fi, w, _ = MeshQuery(truth.vertices, tf, spacing=0.02).closest(X0)
    P = np.einsum("nk,nkd->nd", w, truth.vertices[tf[fi]])

    def area(X):
        return 0.5 * np.linalg.norm(np.cross(X[f[:, 1]] - X[f[:, 0]], X[f[:, 2]] - X[f[:, 0]]), axis=1)

    a0, alpha = area(X0), np.where(t.boundary[ids], 0.0, 1.0)
    for _ in range(30):
        X = X0 + alpha[:, None] * (P - X0)
        bad = area(X) < keep_area * a0
        if not bad.any():
            break
        alpha[np.unique(f[bad])] *= 0.5
    V = t.vertices.copy()
    V[ids] = X
    return V


def keep_garment(t, keep: np.ndarray):
    """``t`` without the garment vertices outside ``keep`` (and their faces)."""
    from physavatar.capture import Template

    k = (t.labels == 0) | keep
    r = -np.ones(len(t.vertices), np.int64)
    r[k] = np.arange(k.sum())
    return Template(t.vertices[k], r[t.faces[k[t.faces].all(1)]], t.labels[k], t.boundary[k], None, None)


def strap_sections(t, heights=STRAP_Z, min_abs_x: float = 0.02) -> dict:
    """Plane sections of ``t``'s garment at each height: the summed segment length (cm) in each of
    the four quadrants left/right (x < 0 / > 0, |x| > ``min_abs_x``) × front/back (y < 0 / > 0)."""
    import trimesh

    ids, f, _ = garment_normals(t)
    m = trimesh.Trimesh(t.vertices[ids], f, process=False)
    out = {}
    for z in heights:
        seg = trimesh.intersections.mesh_plane(m, [0, 0, 1], [0, 0, z])
        mid, length = seg.mean(1), np.linalg.norm(seg[:, 1] - seg[:, 0], axis=1)
        cells = {}
        for sx, side in ((-1, "left"), (1, "right")):
            for sy, part in ((-1, "front"), (1, "back")):
                sel = (np.sign(mid[:, 0]) == sx) & (np.sign(mid[:, 1]) == sy) & (np.abs(mid[:, 0]) > min_abs_x)
                cells[f"{side}_{part}"] = round(float(length[sel].sum() * 100), 2)
        out[f"{z:.2f}"] = cells
    return out


def drop_profile(seq: np.ndarray, frame: int = 8) -> dict:
    """Mean z displacement (mm) of the garment from held-out frame 0 to ``frame``, by frame-0 height band."""
    z0 = seq[0, :, 2]
    out = {"all": round(float((seq[frame, :, 2] - z0).mean() * 1e3), 2)}
    for lo, hi in zip(DROP_BANDS[:-1], DROP_BANDS[1:]):
        m = (z0 >= lo) & (z0 < hi)
        if m.any():
            out[f"{lo:.2f}-{hi:.2f}"] = round(float((seq[frame, m, 2] - z0[m]).mean() * 1e3), 2)
    return out


@contextlib.contextmanager
def flat_bending():
    """The simulator's hinge rest angles 0 (flat rest) inside the block (a diagnostic)."""
    from physavatar.sim import energies

    init = energies.Bending.__init__

    def flat(self, topo, k):
        init(self, topo, k)
        self.rest_angle = np.zeros_like(self.rest_angle)

    energies.Bending.__init__ = flat
    try:
        yield
    finally:
        energies.Bending.__init__ = init


def variants(orig, prep) -> dict:
    """name -> (description, template maker, keywords): every variant on the true body (orig's)."""
    from physavatar.stages.prepare.boundary import boundary_from_points

    to, tp = orig.template, prep.template
    tb, pb = to.vertices[to.boundary], tp.vertices[tp.boundary]

    def remeshed():
        import gpytoolbox as gp
        from physavatar.capture import Template

        ids, f, _ = garment_normals(to)
        V, F = gp.remesh_botsch(np.ascontiguousarray(to.vertices[ids]), np.ascontiguousarray(f, np.int32),
                                i=10, h=0.02, project=True)
        bo = to.labels == 0
        nb = int(bo.sum())
        rb = -np.ones(len(to.vertices), np.int64)
        rb[bo] = np.arange(nb)
        Va = np.concatenate([to.vertices[bo], V])
        lab = np.r_[np.zeros(nb, np.int64), np.ones(len(V), np.int64)]
        return Template(Va, np.concatenate([rb[to.faces[bo[to.faces].all(1)]], F + nb]), lab,
                        (lab > 0) & boundary_from_points(Va, tb, 0.012), None, None)

    def hem_cut():
        from physavatar.geometry.closest import MeshQuery

        pf = tp.faces[(tp.labels[tp.faces] > 0).all(1)]
        d, *_ = MeshQuery(tp.vertices, pf, spacing=0.02).closest(to.vertices)
        miss = (to.labels > 0) & (d > 0.01) & (to.vertices[:, 2] < 0.35)
        return keep_garment(to, (to.labels > 0) & ~miss)

    def proj_true_boundary():
        V = onto_truth(tp, to)
        return _template(tp, V, (tp.labels > 0) & boundary_from_points(V, tb, 0.012))

    def necked():  # the left front strap's outer column at z 1.26-1.35 m removed: 2-3.4 cm wide there
        V = to.vertices
        cut = (to.labels > 0) & (V[:, 0] < -0.095) & (V[:, 1] < 0) & (V[:, 2] > 1.26) & (V[:, 2] < 1.35) & ~to.boundary
        return keep_garment(to, (to.labels > 0) & ~cut)

    own = {"own_truth": True}
    return {
        "original": ("the original garment (own truth)", lambda: to, own),
        "original, carried truth": ("the original, scored through carry_truth as a prepared one", lambda: to, {}),
        "original remeshed 2 cm": ("the original garment remeshed (remesh_botsch, h 2 cm), boundary within 1.2 cm",
                                   remeshed, {}),
        "original + smooth noise 2.5 mm": ("template and rest shape moved along the normals, 20 rounds smoothed",
                                           lambda: _template(to, normal_noise(to, 2.5, 20)), {"truth_on": to}),
        "original + smooth noise 2.5 mm, start only": (
            "the same start, rest shape the original's",
            lambda: _template(to, normal_noise(to, 2.5, 20), rest=to.vertices), {"truth_on": to}),
        "original + rough noise 2 mm": ("template and rest shape moved along the normals, per vertex",
                                        lambda: _template(to, normal_noise(to, 2.0, 0)), {"truth_on": to}),
        "original + 3 mm out": ("template and rest shape 3 mm out along the normals (boundary kept)",
                                lambda: _template(to, offset_out(to, 3.0)), {"truth_on": to}),
        "original, rest Taubin 10": ("rest shape Taubin-smoothed 10 rounds (straps' rest area -20 %)",
                                     lambda: _template(to, rest=taubin_rest(to)), {"truth_on": to}),
        "original without the hem the prepared misses": ("its vertices below 0.35 m over 1 cm from the prepared garment removed",
                                                         hem_cut, {"truth_self": True}),
        "original, left front strap necked": ("the left front strap's outer vertices at z 1.26-1.35 m removed "
                                              "(2.0-3.4 cm wide there, as the prepared straps' necks)", necked,
                                              {"truth_self": True}),
        "original, prepared holds": ("boundary: its vertices within 2 cm of the prepared boundary points",
                                     lambda: _template(to, boundary=(to.labels > 0) & boundary_from_points(to.vertices, pb, 0.02)), {}),
        "prepared": ("the prepared garment (true body given to prepare)", lambda: tp, {}),
        "prepared, rest Taubin 10": ("its rest shape Taubin-smoothed", lambda: _template(tp, rest=taubin_rest(tp)),
                                     {"truth_on": tp}),
        "prepared, flat bending rest": ("its hinges' rest angles 0", lambda: tp, {"flat": True}),
        "prepared on the true surface": ("its garment vertices moved onto the true surface (start and rest)",
                                         lambda: _template(tp, onto_truth(tp, to)), {"truth_on": tp}),
        "prepared on the true surface, true holds": ("the same, boundary within 1.2 cm of the true one",
                                                     proj_true_boundary, {"truth_on": tp}),
    }


def parts_arguments(ap: argparse.ArgumentParser, results: Path) -> None:
    """The options of the benchmarks that wear variants of the excerpt's garment on its true body
    (this one and prepare_hold_parts.py)."""
    ap.add_argument("--original", type=Path, required=True)
    ap.add_argument("--prepared-true", type=Path, required=True, help="the excerpt prepared with its true body.npz")
    ap.add_argument("--work", type=Path, required=True)
    ap.add_argument("--only", default="")
    ap.add_argument("--results", type=Path, default=results)


def parts_inputs(args) -> tuple:
    """(load average now, the original's ground_truth/ folder, its true material, the original
    capture, the prepared one) of :func:`parts_arguments`' options."""
    from physavatar.capture import load_capture
    from physavatar.sim.material import Material

    gt_src = args.original / "ground_truth"
    return (os.getloadavg(), gt_src, Material.load(gt_src / "material.json"), load_capture(args.original),
            load_capture(args.prepared_true))


def main() -> int:
    ap = argparse.ArgumentParser()
    parts_arguments(ap, HERE / "results" / "prepare_garment_parts_s33.json")
    args = ap.parse_args()
    from physavatar.files import load_npz

    load0, gt_src, mat, orig, prep = parts_inputs(args)
    only = [s for s in args.only.split(",") if s]
    results = {}
    for name, (what, make, kw) in variants(orig, prep).items():
        if only and name not in only:
            continue
        w = args.work / name.replace(" ", "_").replace(",", "")
        cached = w / "result.json"
        if cached.is_file():
            r = json.loads(cached.read_text())
        else:
            w.mkdir(parents=True, exist_ok=True)
            t = make()
            kw = dict(kw)
            flat = kw.pop("flat", False)
            if kw.pop("truth_self", False):
                kw["truth_on"] = t
            cap = dataclasses.replace(orig, template=t)
            with flat_bending() if flat else contextlib.nullcontext():
                r = heldout_cd(cap, gt_src, mat, w, None, keep_sequence=True, **kw)
            seq = r.pop("_sequence")
            r |= {"what": what, "drop_frame8_mm": drop_profile(seq), "strap_sections_cm": strap_sections(t)}
            cached.write_text(json.dumps(r, indent=1) + "\n")
        results[name] = r
        print(f"{name:48s} held-out garment CD x1e3 {r['chamfer_x1e3']:.4f}  F@1cm {r['fscore@1cm']:.3f}  "
              f"drop@8 {r['drop_frame8_mm']['all']:.1f} mm", flush=True)
    truth = load_npz(gt_src / "heldout" / "meshes.npz")["vertices"].astype(np.float64)
    g = orig.template.labels > 0
    write_heldout_result(args.results, "prepare_garment_parts", load0,
                         {"original": str(args.original), "prepared_true": str(args.prepared_true),
                          "material": mat.to_dict(), "truth_drop_frame8_mm": drop_profile(truth[:, g])},
                         results, "Chamfer x1e3 (true material, true body)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
