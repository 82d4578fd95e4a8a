"""Garment templates: mesh quality, topology, no contact with the body, boundary attachments,
skinning weights, UVs, the edge-length parameter and the combined capture template."""

import numpy as np
import pytest
import trimesh

from physavatar.body import BodyModel, linear_blend_skinning
from physavatar.capture import check_template_mesh
from physavatar.files import read_ply
from physavatar.garment import (Garment, MIN_CLEARANCE, attachment_positions, combine_template,
                                garment_skinning_weights, make_attachment, make_garment)
from physavatar.geometry import MeshQuery, count_intersections

KINDS = ("dress", "skirt", "tshirt")
# open boundary loops: dress (hem, neck, two armholes), skirt (hem, waist), T-shirt (hem, neck, sleeves)
LOOPS = {"dress": 4, "skirt": 2, "tshirt": 4}


@pytest.fixture(scope="module")
def body():
    return BodyModel(topology="full")


@pytest.fixture(scope="module")
def collider(body):
    return BodyModel(body.shape, topology="collider")


@pytest.fixture(scope="module")
def garments(body):
    return {k: make_garment(k, body, edge_length=0.02) for k in KINDS}


def _boundary_loops(F, n):
    e = np.sort(np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]]), axis=1)
    u, c = np.unique(e, axis=0, return_counts=True)
    b = u[c == 1]
    import scipy.sparse as sp
    from scipy.sparse.csgraph import connected_components

    A = sp.coo_matrix((np.ones(len(b)), (b[:, 0], b[:, 1])), shape=(n, n))
    _, lab = connected_components(A, directed=False)
    return len(np.unique(lab[np.unique(b)]))


@pytest.mark.parametrize("kind", KINDS)
def test_mesh_quality_and_topology(garments, kind):
    g = garments[kind]
    q = g.quality()
    # Triangle meshes each panel at >= 30 deg in pattern space; lifting it onto the body and
    # sewing the seams costs a few degrees at single triangles, and which ones is chaotic in the
    # body's last bits: the 2-cm dress's worst triangle is 26.0 deg in docs/garments.md, 25.7 on an
    # AMD EPYC with anny 0.6.1 and 23.2 there with anny 0.6.2 (the rest body equal to 1e-12),
    # while its 0.1st percentile stays at 29.2-29.3 deg. So: no sliver anywhere, and at most
    # 0.2 % of the triangles under 25 deg.
    assert q["min_angle_deg"] >= 20.0, q
    tm = trimesh.Trimesh(g.vertices, g.faces, process=False)
    worst = np.degrees(tm.face_angles.min(1))
    assert (worst < 25.0).mean() <= 0.002, (int((worst < 25.0).sum()), len(worst))
    assert q["area_ratio"] <= 4.0, q
    assert abs(q["mean_edge"] - 0.02) < 0.003, q
    # independent angle check (trimesh)
    assert np.degrees(tm.face_angles.min()) == pytest.approx(q["min_angle_deg"], abs=1e-6)
    assert check_template_mesh(g.vertices, g.faces) == []
    assert len(tm.split(only_watertight=False)) == 1  # seams closed: one piece of cloth
    loops = _boundary_loops(g.faces, len(g.vertices))
    assert loops == LOOPS[kind]
    # a sphere with `loops` holes: V - E + F = 2 - loops (no handles, nothing left open at a seam)
    assert tm.euler_number == 2 - loops
    if kind == "dress":
        assert 2000 <= q["n_vertices"] <= 3500  # the simulator's speed target


@pytest.mark.parametrize("kind", KINDS)
def test_no_intersection_and_clearance(garments, body, collider, kind):
    g = garments[kind]
    for b in (body, collider):
        assert count_intersections(g.vertices, g.faces, b.rest_vertices, b.faces) == 0
        sd, q, _ = MeshQuery(b.rest_vertices, b.faces).signed_distance(g.vertices)
        assert sd.min() >= MIN_CLEARANCE - 1e-9  # outside and clear of the body
        # the closest pair's distance agrees with ipctk's point-triangle distance
        import ipctk

        i = int(np.argmin(sd))
        d, f, _, _ = MeshQuery(b.rest_vertices, b.faces).closest(g.vertices[i:i + 1])
        t = b.rest_vertices[b.faces[f[0]]]
        assert np.sqrt(ipctk.point_triangle_distance(g.vertices[i], t[0], t[1], t[2])) == pytest.approx(d[0], abs=1e-9)
    assert g.clearance >= MIN_CLEARANCE - 1e-9
    assert g.quality()["min_clearance_m"] == g.clearance
    # the intersection test can fail: the same garment pushed 4 cm backwards cuts into the body
    assert count_intersections(g.vertices + [0.0, 0.04, 0.0], g.faces, body.rest_vertices, body.faces) > 0


def test_closest_points_match_brute_force(collider):
    rng = np.random.default_rng(0)
    P = collider.rest_vertices[rng.integers(0, len(collider.rest_vertices), 200)] + rng.normal(0, 0.05, (200, 3))
    d, f, w, q = MeshQuery(collider.rest_vertices, collider.faces).closest(P)
    ref_q, ref_d, _ = trimesh.proximity.closest_point_naive(trimesh.Trimesh(collider.rest_vertices, collider.faces,
                                                                            process=False), P)
    assert np.abs(d - ref_d).max() < 1e-9
    assert np.allclose(w.sum(1), 1.0) and (w >= -1e-12).all()


@pytest.mark.parametrize("kind", KINDS)
def test_boundary_where_the_garment_hangs(garments, body, kind):
    g = garments[kind]
    B = g.vertices[g.boundary]
    assert len(B) >= 8
    joint = dict(zip(body.bone_names, body.rest_joints))
    if kind == "skirt":  # the waistband ring, all the way round
        zw = joint["spine03"][2]
        assert (np.abs(B[:, 2] - zw) < 0.03).all()
        ang = np.arctan2(B[:, 1] - B[:, 1].mean(), B[:, 0])
        assert np.histogram(ang, bins=8, range=(-np.pi, np.pi))[0].min() > 0
    else:  # on the shoulder tops, both sides, front and back
        assert (B[:, 2] > joint["upperarm02.L"][2]).all()
        assert (np.abs(B[:, 0]) < joint["upperarm01.L"][0] + 0.035).all()
        assert (B[:, 0] > 0).any() and (B[:, 0] < 0).any()
        assert np.ptp(B[:, 1]) > 0.03  # spans the shoulder from front to back
    assert np.array_equal(np.sort(g.attachment.vertex_ids), np.nonzero(g.boundary)[0])


@pytest.mark.parametrize("kind", KINDS)
def test_uvs_from_the_pattern(garments, kind):
    g = garments[kind]
    uv = g.face_uvs
    assert uv.shape == (len(g.faces), 3, 2)
    assert uv.min() >= 0.0 and uv.max() <= 1.0
    # the pattern is a near-isometric flattening: 3D area / UV area is nearly constant
    a3 = trimesh.Trimesh(g.vertices, g.faces, process=False).area_faces
    e1, e2 = uv[:, 1] - uv[:, 0], uv[:, 2] - uv[:, 0]
    a2 = 0.5 * (e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0])
    assert (a2 > 0).all()  # no folded or mirrored triangles in the atlas
    r = a3 / a2
    lo, hi = np.percentile(r, [2, 98])
    assert hi / lo < 1.6


def test_attachment_reproduces_rest_and_follows_the_body(garments, body, collider):
    g = garments["dress"]
    att = g.attachment
    assert att.topology == "full"
    rest = attachment_positions(att, body.rest_vertices[None])
    assert np.abs(rest[0] - g.vertices[att.vertex_ids]).max() < 1e-10
    # attachment to the collider topology reproduces its points too
    ids = np.nonzero(g.boundary)[0]
    att_c = make_attachment(g.vertices[ids], ids, collider.rest_vertices, collider.faces, "collider")
    assert np.abs(attachment_positions(att_c, collider.rest_vertices) - g.vertices[ids]).max() < 1e-10
    # posed: shoulders shrug, torso bends and turns; the attached points keep their distance to the body
    R, t = body.rest_pose(2)
    names = body.bone_names
    R[1, names.index("spine02")] = [0.25, 0.0, 0.3]
    R[1, names.index("clavicle.L")] = [0.0, -0.25, 0.0]
    R[1, names.index("clavicle.R")] = [0.0, 0.2, 0.0]
    t[1] = [0.1, -0.05, 0.02]
    posed = body.pose(R, t).vertices
    P = attachment_positions(att, posed)
    d_rest = MeshQuery(body.rest_vertices, body.faces).closest(rest[0])[0]
    d_posed = MeshQuery(posed[1], body.faces).closest(P[1])[0]
    assert np.abs(d_posed - d_rest).max() < 1e-3
    assert np.abs(P[0] - rest[0]).max() < 1e-10
    assert np.linalg.norm(P[1] - rest[0], axis=1).max() > 0.05  # it did move with the body


def test_skinning_weights(garments, body):
    g = garments["skirt"]
    W = garment_skinning_weights(g.vertices, body, g.faces)
    assert W.shape == (len(g.vertices), len(body.bone_names))
    assert (W >= 0).all() and np.allclose(W.sum(1), 1.0, atol=1e-12)
    R, t = body.rest_pose(2)
    R[1, 0] = [0.3, -0.2, 0.5]
    t[1] = [0.2, 0.1, 0.0]
    posed = body.pose(R, t)
    X = linear_blend_skinning(g.vertices, W, posed.bone_transforms)
    assert np.abs(X[0] - g.vertices).max() < 1e-9  # rest pose: the rest garment
    # a root-only motion is rigid, and rows summing to one reproduce it exactly
    from physavatar.body import axis_angle_to_matrix

    h = body.rest_joints[0]
    expect = (g.vertices - h) @ axis_angle_to_matrix(R[1, 0]).T + h + t[1]
    assert np.abs(X[1] - expect).max() < 1e-9
    # smoothing over the cloth: neighbouring vertices' weights differ less than raw closest-point weights
    raw = garment_skinning_weights(g.vertices, body, None)
    e = np.unique(np.sort(np.concatenate([g.faces[:, [0, 1]], g.faces[:, [1, 2]]]), axis=1), axis=0)
    jump = lambda w: np.abs(w[e[:, 0]] - w[e[:, 1]]).sum(1).max()  # noqa: E731
    assert jump(W) < 0.7 * jump(raw)


def test_edge_length_sets_resolution(garments, body):
    g2 = garments["skirt"]
    n2 = g2.quality()["n_vertices"]
    for h in (0.04,):  # 1 cm works too (docs/garments.md), but costs 10 s here
        g = make_garment("skirt", body, edge_length=h)
        q = g.quality()
        assert abs(q["mean_edge"] - h) < 0.15 * h, q
        expect = n2 * (0.02 / h) ** 2  # vertices ~ area / h²
        assert 0.75 * expect < q["n_vertices"] < 1.3 * expect, (h, q)
        assert q["min_angle_deg"] >= 25.0 and q["area_ratio"] <= 4.0, q
        assert check_template_mesh(g.vertices, g.faces) == []


def test_combined_template(garments, body, tmp_path):
    gs = [garments["dress"]]
    tpl = combine_template(body, None, None, gs)
    assert check_template_mesh(tpl.vertices, tpl.faces) == []
    nb = len(body.rest_vertices)
    assert (tpl.labels[:nb] == 0).all() and (tpl.labels[nb:] == 1).all()
    assert not tpl.boundary[:nb].any() and tpl.boundary[nb:].sum() == gs[0].boundary.sum()
    assert tpl.face_uvs.min() >= 0 and tpl.face_uvs.max() <= 1
    # garment charts sit right of the body's strip in the atlas
    assert tpl.face_uvs[len(body.faces):, :, 0].min() >= 0.25 > tpl.face_uvs[: len(body.faces), :, 0].max()
    tpl.save(tmp_path / "mesh.ply")
    ply = read_ply(tmp_path / "mesh.ply")
    assert np.allclose(ply.vertices, tpl.vertices, atol=1e-6) and np.array_equal(ply.faces, tpl.faces)
    assert np.allclose(ply.face_uvs, tpl.face_uvs, atol=1e-6)
    two = combine_template(body, None, None, [garments["tshirt"], garments["dress"]])
    assert set(np.unique(two.labels)) == {0, 1, 2}


def test_garment_value_object(garments, tmp_path):
    g = garments["tshirt"]
    g.save(tmp_path / "t.npz")
    h = Garment.load(tmp_path / "t.npz")
    assert np.array_equal(h.faces, g.faces) and np.allclose(h.vertices, g.vertices)
    assert np.array_equal(h.boundary, g.boundary) and h.attachment.topology == g.attachment.topology
    assert h.quality() == g.quality()
    with pytest.raises(ValueError, match="boundary"):
        Garment("x", g.vertices, g.faces, g.face_uvs, np.zeros(len(g.vertices), bool), g.attachment, 0.02)
    with pytest.raises(ValueError, match="unknown garment"):
        make_garment("hat", BodyModel(topology="collider"))
