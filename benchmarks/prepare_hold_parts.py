"""Which property of the prepared holds costs the held-out Chamfer (issue 23, session 35).

    python benchmarks/prepare_hold_parts.py --original EXCERPT --prepared-true PREP_T --work W \
        [--prepare-input NAME=DIR ...] [--only "NAME;..."] [--results benchmarks/results/prepare_hold_parts_s35.json]

As `prepare_garment_parts.py` (session 33): every variant is the ORIGINAL garment of the excerpt
worn on the true body with the true material and scored against its own held-out truth
(:func:`prepare_heldout_parts.heldout_cd`); only its boundary (the holds) changes. The true holds
are the demo dress's 58 strap vertices over the shoulders; the prepared holds are the original's
vertices within 2 cm of ``PREP_T``'s boundary points (session 33's row). Variants split the
difference: the true holds without those prepare misses, with those it adds, front or back of
the shoulder's top only, shifted along z, the top rows only, grown by a ring. Per variant also the
hold set's extent (y range, z range) and the mean drop at held-out frame 8 by height.

``--prepare-input NAME=DIR`` (repeatable): DIR is the excerpt without template/ and with a body.npz
(the true one, or a fitted one); it is prepared (W/prepared_NAME) with `find_boundary`'s inputs
recorded (the garment's contact-test positions, the body, each vertex's body distance and carried
support), and the PREPARED garment is then simulated (its body.npz, the true material, the truth
carried onto it) with the holds of other rules on those same inputs: its own (the z band), grown
along the garment over the contact vertices by 2 or 3 cm (geodesic, no z limit), a band of 7 cm
along the garment from each hold's crest (its vertices within 1 cm of its top), the contact joined
to the holds where the body's normal points up (n_z > 0.5), and the true holds (its vertices
within 2 cm of a true one).
Writes ``checks`` (reported figures, no target); W/NAME/result.json caches each variant.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
from _common import write_heldout_result
from prepare_garment_parts import _template, drop_profile, parts_arguments, parts_inputs
from prepare_heldout_parts import heldout_cd


def _slug(name: str) -> str:
    return "".join(c if c.isalnum() or c in "._-" else "_" for c in name)


def hold_sets(orig, prep) -> dict:
    """name -> (description, [V] bool boundary on the original template)."""
    from physavatar.geometry.mesh import adjacency
    from physavatar.stages.prepare.boundary import boundary_from_points

    to, tp = orig.template, prep.template
    V, g, tb = to.vertices, to.labels > 0, to.boundary
    ph = g & boundary_from_points(V, tp.vertices[tp.boundary], 0.02)
    P = V[tb]

    def near(points, r=0.012):
        return g & boundary_from_points(V, points, r)

    A = adjacency(to.faces, len(V))
    ring = g & (np.asarray(A @ tb.astype(np.int64)).ravel() > 0) | tb
    top = tb & (V[:, 2] >= V[tb, 2].max() - 0.02)
    return {
        "true holds": ("the excerpt's own boundary (58 strap vertices over the shoulders)", tb),
        "prepared holds": ("its vertices within 2 cm of the prepared boundary points (session 33)", ph),
        "true and prepared": ("the true holds prepare also picks (true minus what it misses)", tb & ph),
        "true or prepared": ("the true holds plus what prepare adds (front, 1-2 cm below)", tb | ph),
        "true, front half": ("the true holds in front of the shoulder's top (y < 0.01 m)", tb & (V[:, 1] < 0.01)),
        "true, back half": ("the true holds behind the shoulder's top (y > 0.01 m)", tb & (V[:, 1] > 0.01)),
        "true without the back slope": ("the true holds with y < 0.03 m (the prepared holds' back edge)",
                                        tb & (V[:, 1] < 0.03)),
        "true, top 2 cm": ("the true holds within 2 cm of their highest", top),
        "true shifted down 1 cm": ("garment vertices within 1.2 cm of the true holds moved 1 cm down",
                                   near(P - [0, 0, 0.01])),
        "true shifted forward 2 cm": ("garment vertices within 1.2 cm of the true holds moved 2 cm forward (-y)",
                                      near(P - [0, 0.02, 0])),
        "true grown one ring": ("the true holds and their garment neighbours", ring),
    }


def record_boundary_inputs(src: Path, dst: Path) -> dict:
    """Prepares ``src`` into ``dst`` (default settings, ``boundary.grow_along`` 0: the holds of
    session 34's main, the z band) and returns find_boundary's inputs for its
    one garment piece: V (the contact-test positions), F, BV (the first sampled frame's body), BF,
    d (body distance), worst (carried support); cached in ``dst``/boundary_inputs.npz."""
    cache = dst / "boundary_inputs.npz"
    if not cache.is_file():
        from physavatar.stages.prepare import PrepareConfig
        from physavatar.stages.prepare import boundary as B
        from physavatar.stages.prepare.config import BoundaryConfig
        from physavatar.stages.prepare import run as prepare

        orig, got = B.find_boundary, {}

        def record(vertices, faces, body_frames, body_faces, cameras, masks_of, frame_index, cfg):
            worst, (d, *_) = B.carried_support(vertices, body_frames, body_faces, cameras, masks_of)
            got.update(V=vertices, F=faces, BV=body_frames[0], BF=body_faces, d=d, worst=worst)
            return orig(vertices, faces, body_frames, body_faces, cameras, masks_of, frame_index, cfg)

        B.find_boundary = record
        try:
            prepare(src, out=dst, config=PrepareConfig(boundary=BoundaryConfig(grow_along=0.0)), progress=False)
        finally:
            B.find_boundary = orig
        np.savez(cache, **got)
    return dict(np.load(cache))


def rule_sets(prep, truth, D: dict) -> dict:
    """name -> [V] bool boundary on ``prep``'s template from other hold rules on the recorded
    find_boundary inputs ``D`` (the template's garment vertices are D's, in order)."""
    import scipy.sparse as sp
    import trimesh
    from scipy.sparse.csgraph import connected_components, dijkstra

    from physavatar.geometry.closest import MeshQuery
    from physavatar.geometry.mesh import adjacency
    from physavatar.stages.prepare.boundary import along_garment, boundary_from_points

    tp = prep.template
    gi = np.flatnonzero(tp.labels > 0)
    V, F = D["V"], D["F"]
    if len(gi) != len(V):
        raise SystemExit("the prepared garment is not the recorded piece (fragments dropped?)")
    A = adjacency(F, len(V)).tocsr()
    own, contact = tp.boundary[gi], D["d"] < 0.02
    _, fi, _, _ = MeshQuery(D["BV"], D["BF"], spacing=0.02).closest(V)
    nz = trimesh.Trimesh(D["BV"], D["BF"], process=False).face_normals[fi][:, 2]

    def geo(seed, allowed, r):  # allowed vertices within geodesic r of seed (through allowed ones)
        i, j = A.nonzero()
        ok = allowed[i] & allowed[j]
        G = sp.csr_matrix((np.linalg.norm(V[i] - V[j], axis=1)[ok], (i[ok], j[ok])), shape=A.shape)
        return seed | (allowed & (dijkstra(G, directed=False, indices=np.flatnonzero(seed), min_only=True) <= r))

    def joined(seed, allowed):  # the components of allowed that hold a seed vertex
        idx = np.flatnonzero(allowed)
        k, lab = connected_components(A[idx][:, idx], directed=False)
        hit = np.zeros(k, bool)
        np.maximum.at(hit, lab, seed[idx])
        out = np.zeros(len(V), bool)
        out[idx[hit[lab]]] = True
        return out

    def crest(r, band=0.01):
        reg = joined(own, contact)
        idx = np.flatnonzero(reg)
        k, lab = connected_components(A[idx][:, idx], directed=False)
        top = np.full(k, -np.inf)
        np.maximum.at(top, lab, V[idx, 2])
        seed = np.zeros(len(V), bool)
        seed[idx[V[idx, 2] >= top[lab] - band]] = True
        return geo(seed, reg, r)

    sets = {"own": ("its own holds (the z band: session 34's main, grow_along 0)", own),
            "grown 2 cm over contact": ("its holds grown 2 cm along the garment over contact vertices "
                                        "(along_garment: the setting grow_along 0.02)",
                                        along_garment(V, F, own, contact, 0.02)),
            "grown 3 cm over contact": ("the same, 3 cm", along_garment(V, F, own, contact, 0.03)),
            "crest 7 cm": ("contact within 7 cm along the garment of each hold's crest (its top 1 cm)", crest(0.07)),
            "contact joined, n_z > 0.5": ("the contact joined to its holds where the body normal's z > 0.5",
                                          joined(own, contact & (nz > 0.5)) | own),
            "true holds": ("its vertices within 2 cm of a true hold",
                           boundary_from_points(tp.vertices[gi], truth.vertices[truth.boundary], 0.02))}
    out = {}
    for k, (what, b) in sets.items():
        full = np.zeros(len(tp.vertices), bool)
        full[gi] = b
        out[k] = (what, full)
    return out


def _run(name, what, cap, b, gt_src, mat, w, **kw):
    """The variant's cached or new result (held-out Chamfer, drop, the holds' extent)."""
    cached = w / "result.json"
    if cached.is_file():
        r = json.loads(cached.read_text()) | {"what": what}
    else:
        w.mkdir(parents=True, exist_ok=True)
        cap = dataclasses.replace(cap, template=_template(cap.template, boundary=b))
        r = heldout_cd(cap, gt_src, mat, w, None, keep_sequence=True, **kw)
        seq = r.pop("_sequence")
        H = cap.template.vertices[b]
        r |= {"what": what, "drop_frame8_mm": drop_profile(seq),
              "holds_y_m": [round(float(H[:, 1].min()), 3), round(float(H[:, 1].max()), 3)],
              "holds_z_m": [round(float(H[:, 2].min()), 3), round(float(H[:, 2].max()), 3)]}
        cached.write_text(json.dumps(r, indent=1) + "\n")
    print(f"{name:44s} holds {r['boundary_vertices']:3d}  held-out garment CD x1e3 {r['chamfer_x1e3']:.4f}  "
          f"F@1cm {r['fscore@1cm']:.3f}  drop@8 {r['drop_frame8_mm']['all']:.1f} mm", flush=True)
    return r


def main() -> int:
    ap = argparse.ArgumentParser()
    parts_arguments(ap, HERE / "results" / "prepare_hold_parts_s35.json")
    ap.add_argument("--prepare-input", action="append", default=[], metavar="NAME=DIR",
                    help="the excerpt without template/ and with a body.npz, to prepare and try hold rules on")
    args = ap.parse_args()
    from physavatar.capture import load_capture

    load0, gt_src, mat, orig, prep = parts_inputs(args)
    only = [s for s in args.only.split(";") if s]
    results = {}
    for name, (what, b) in hold_sets(orig, prep).items():
        if not only or name in only:
            results[name] = _run(name, what, orig, b, gt_src, mat, args.work / _slug(name), own_truth=True)
    from physavatar.stages.prepare.boundary import boundary_error

    errors = {}
    for spec in args.prepare_input:
        tag, src = spec.split("=", 1)
        dst = args.work / f"prepared_{tag}"
        D = record_boundary_inputs(Path(src), dst)
        pc = load_capture(dst)
        errors[tag] = {}
        for rule, (what, b) in rule_sets(pc, orig.template, D).items():
            name = f"prepared ({tag}), {rule}"
            e = boundary_error(pc.template.vertices[b], orig.template.vertices[orig.template.boundary])
            errors[tag][rule] = {k: round(v * 100, 2) for k, v in e.items()} | {"holds": int(b.sum())}
            if not only or name in only:
                results[name] = _run(name, what, pc, b, gt_src, mat, args.work / _slug(name)) | {
                    "boundary_error_cm": errors[tag][rule]}
    write_heldout_result(args.results, "prepare_hold_parts", load0,
                         {"original": str(args.original), "prepared_true": str(args.prepared_true),
                          "material": mat.to_dict(),
                          "prepare_inputs": args.prepare_input, "boundary_error_cm": errors}, results, "Chamfer x1e3 (true material, true body)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
