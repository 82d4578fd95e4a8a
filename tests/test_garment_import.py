"""Garments from other tools' files (physavatar.garment.files), their seams held by the stitch
term (physavatar.sim.stitch), the automatic boundary (garment.boundary) and the start repair
(sim.start.repair_start), against analytic expectations and finite differences."""

import ipctk
import numpy as np
import pytest
import trimesh
from typer.testing import CliRunner

from physavatar.cli import app
from physavatar.errors import PhysavatarError
from physavatar.files import PlyMesh, write_ply
from physavatar.garment.boundary import auto_boundary
from physavatar.garment.files import load_garment
from physavatar.sim import SimSettings, preset
from physavatar.sim.contact import ContactScene
from physavatar.sim.simulate import simulate
from physavatar.sim.start import repair_start
from physavatar.sim.stitch import Stitch, seam_gaps

runner = CliRunner()


def panel(x0, width, height, n, y=0.0):
    """A flat (n+1)×(n+1) grid panel in the x–z plane at y: vertices [(n+1)², 3], faces."""
    u, v = np.meshgrid(np.linspace(0, 1, n + 1), np.linspace(0, 1, n + 1), indexing="ij")
    V = np.stack([x0 + width * u.ravel(), np.full(u.size, y), height * v.ravel()], axis=1)
    idx = np.arange(u.size).reshape(n + 1, n + 1)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    return V, np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])


def two_panels(n=4, rest_width=0.18):
    """Two 0.2 m panels side by side in the world (meeting along x = 0.2), and their rest
    panels, narrower (``rest_width``), laid apart in a material plane (z = 0)."""
    Va, Fa = panel(0.0, 0.2, 0.2, n)
    Vb, Fb = panel(0.2, 0.2, 0.2, n)
    Ra, _ = panel(0.0, rest_width, 0.2, n)
    Rb, _ = panel(1.0, rest_width, 0.2, n)
    world = np.vstack([Va, Vb])
    rest = np.vstack([Ra, Rb])[:, [0, 2, 1]]  # material coordinates in x–y
    faces = np.vstack([Fa, Fb + len(Va)])
    return world, rest, faces


def write_obj(path, V, F, vt=None):
    with open(path, "w") as f:
        f.writelines(f"v {v[0]:.9g} {v[1]:.9g} {v[2]:.9g}\n" for v in V)
        if vt is not None:
            f.writelines(f"vt {t[0]:.9g} {t[1]:.9g}\n" for t in vt.reshape(-1, 2))
            f.writelines("f " + " ".join(f"{i + 1}/{3 * k + c + 1}" for c, i in enumerate(tri)) + "\n" for k, tri in enumerate(F))
        else:
            f.writelines("f " + " ".join(str(i + 1) for i in tri) + "\n" for tri in F)


def edge_lengths(V, F):
    return np.linalg.norm(V[F[:, [1, 2, 0]]] - V[F], axis=2)


def test_obj_panels_with_a_rest_file_and_coincident_seams(tmp_path):
    world, rest, faces = two_panels(n=4)
    write_obj(tmp_path / "g-w.obj", world, faces)
    write_obj(tmp_path / "g-m.obj", rest, faces)
    g = load_garment(tmp_path / "g-w.obj")  # g-m.obj found beside it (the Berkeley Library's naming)
    assert g.rest_source == "file" and len(g.vertices) == 50 and len(np.unique(g.panels())) == 2
    # the rest shape of every triangle is the rest file's, not the world's (world is 0.2/0.18 wider)
    assert np.allclose(edge_lengths(g.rest, g.faces), edge_lengths(rest, faces), atol=1e-7)
    assert np.allclose(edge_lengths(g.vertices, g.faces), edge_lengths(world, faces), atol=1e-7)
    # the seam: the 5 vertex pairs on x = 0.2, one from each panel
    assert len(g.seams) == 5 and np.all(seam_gaps(g.vertices, g.seams) < 1e-9)
    assert np.allclose(g.vertices[g.seams.ravel(), 0], 0.2)
    assert np.all(g.panels()[g.seams[:, 0]] != g.panels()[g.seams[:, 1]])


def test_combined_obj_with_material_uv_and_a_layered_seam(tmp_path):
    """The Library's combined file: seam vertices merged, material coordinates in vt per corner;
    a third panel folded onto the seam line makes a layered seam (three vertices at one point)."""
    world, rest, faces = two_panels(n=2)
    Vc, Fc = panel(0.2, 0.1, 0.2, 2, y=0.0)  # a third panel from the seam line
    Vc = np.stack([np.full(len(Vc), 0.2), Vc[:, 0] - 0.2, Vc[:, 2]], 1)  # in the y–z plane at x = 0.2
    Rc = np.stack([Vc[:, 1] + 2.0, Vc[:, 2], np.zeros(len(Vc))], 1)
    world = np.vstack([world, Vc])
    rest = np.vstack([rest, Rc])
    faces = np.vstack([faces, Fc + 18])
    merged, inv = np.unique(np.round(world, 9), axis=0, return_inverse=True)
    write_obj(tmp_path / "c.obj", merged, inv.ravel()[faces], vt=rest[faces][:, :, :2])
    g = load_garment(tmp_path / "c.obj")
    assert g.rest_source == "uv" and len(g.vertices) == 27 and len(np.unique(g.panels())) == 3
    assert np.allclose(np.sort(edge_lengths(g.rest, g.faces).ravel()), np.sort(edge_lengths(rest, faces).ravel()))
    # x = 0.2 has 3 vertices in each of the two side panels' column and in the third panel's y = 0 column:
    # every point there is one layered seam group of 3 -> 2 pairs each
    assert len(g.seams) == 6
    assert np.all(np.isclose(g.vertices[g.seams.ravel(), 0], 0.2))


def test_ply_gltf_npz_up_axis_and_units(tmp_path):
    world, rest, faces = two_panels(n=2)
    yup = world[:, [0, 2, 1]] * np.array([1, 1, -1])  # the same garment with y up (x, z, -y)
    trimesh.Trimesh(yup * 100, faces, process=False).export(tmp_path / "g.ply")
    g = load_garment(tmp_path / "g.ply", up="y", scale="cm")
    assert g.rest_source == "world" and np.allclose(np.sort(g.vertices[:, 2]), np.sort(world[:, 2]), atol=1e-6)
    trimesh.Trimesh(yup, faces, process=False).export(tmp_path / "g.glb")  # glTF: y up by convention
    g = load_garment(tmp_path / "g.glb")
    assert np.allclose(np.sort(g.vertices[:, 2]), np.sort(world[:, 2]), atol=1e-6)
    assert np.allclose(np.sort(g.vertices[:, 1]), np.sort(world[:, 1]), atol=1e-6)
    assert len(g.seams) == 3  # coincident vertices of the two panels (a glb keeps them apart)
    np.savez(tmp_path / "g.npz", vertices=world, faces=faces, rest=rest, boundary=np.array([0, 3]),
             seams=np.array([[1, 10]]))
    g = load_garment(tmp_path / "g.npz")
    assert g.rest_source == "file" and np.allclose(g.rest, rest) and set(g.boundary) == {0, 3}
    assert [1, 10] in g.seams.tolist() and len(g.seams) == 4  # the listed pair + the 3 coincident ones


def test_stitch_derivatives_match_finite_differences():
    rng = np.random.default_rng(0)
    x = rng.normal(size=(6, 3))
    term = Stitch([[0, 3], [1, 4], [0, 5]], 7.0, weights=[1.0, 0.5, 2.0])
    g, H = term.gradient(x), term.hessian(x).to_sparse(18).toarray()
    eps = 1e-6
    fd_g, fd_H = np.zeros(18), np.zeros((18, 18))
    for i in range(18):
        d = np.zeros(18)
        d[i] = eps
        fd_g[i] = (term.energy(x.ravel() + d) - term.energy(x.ravel() - d)) / (2 * eps)
        fd_H[:, i] = (term.gradient(x.ravel() + d) - term.gradient(x.ravel() - d)) / (2 * eps)
    assert np.abs(fd_g - g).max() < 1e-6 * np.abs(g).max()
    assert np.abs(fd_H - H).max() < 1e-6 * np.abs(H).max()
    assert np.linalg.eigvalsh(H).min() > -1e-9  # PSD: projection is a no-op
    assert np.isclose(term.energy(x), 0.5 * 7.0 * sum(w * np.sum((x[i] - x[j]) ** 2)
                                                     for (i, j), w in zip([(0, 3), (1, 4), (0, 5)], [1, 0.5, 2])))


@pytest.mark.parametrize("stitched", [True, False])
def test_a_seam_pulled_apart_is_held_by_the_stitch(stitched, tmp_path):
    """Two panels pinned at their outer edges, each 10 % narrower at rest than in the world: sewn,
    the seam stays shut and both stretch uniformly to 0.4 / 0.36 (cotton's Poisson ratio is 0);
    unsewn, each contracts to its rest width and the seam opens by 0.4 − 2 × 0.18 = 4 cm."""
    world, rest, faces = two_panels(n=4)
    write_obj(tmp_path / "g-w.obj", world, faces)
    write_obj(tmp_path / "g-m.obj", rest, faces)
    g = load_garment(tmp_path / "g-w.obj")
    pinned = np.flatnonzero(np.isclose(g.vertices[:, 0], 0.0) | np.isclose(g.vertices[:, 0], 0.4))
    settings = SimSettings(gravity=(0.0, 0.0, 0.0), damping_mass=5.0)
    T = 25
    X = simulate(g.rest, g.faces, preset("cotton"), np.zeros((T, 0, 3)), np.zeros((0, 3), int),
                 boundary_indices=pinned, x0=g.vertices, settings=settings,
                 extra_terms=[Stitch(g.seams)] if stitched else [])
    gap = seam_gaps(X[-1], g.seams)
    if stitched:
        assert gap.max() < 1e-4
        # every horizontal edge stretched by 0.4 / 0.36 (its rest length from the rest file)
        e = g.faces[:, [0, 1]]
        horiz = np.isclose(g.rest[e[:, 0], 1], g.rest[e[:, 1], 1])
        ratio = (np.linalg.norm(X[-1][e[:, 0]] - X[-1][e[:, 1]], axis=1) /
                 np.linalg.norm(g.rest[e[:, 0]] - g.rest[e[:, 1]], axis=1))[horiz]
        assert np.allclose(ratio, 0.4 / 0.36, rtol=0.01)
    else:
        assert np.allclose(gap, 0.04, rtol=0.1)


def cylinder_body(radius=0.15, height=1.0):
    m = trimesh.creation.cylinder(radius=radius, height=height, sections=48)
    m.apply_translation([0, 0, height / 2])
    return np.asarray(m.vertices), np.asarray(m.faces)


def frustum(r_top, r_bottom, z_top, z_bottom, n_around=40, n_down=10):
    a = np.linspace(0, 2 * np.pi, n_around, endpoint=False)
    t = np.linspace(0, 1, n_down + 1)
    r = r_top + (r_bottom - r_top) * t
    z = z_top + (z_bottom - z_top) * t
    V = np.stack([np.outer(r, np.cos(a)).ravel(), np.outer(r, np.sin(a)).ravel(), np.repeat(z, n_around)], 1)
    idx = np.arange(V.shape[0]).reshape(n_down + 1, n_around)
    nxt = np.roll(idx, -1, axis=1)
    F = np.concatenate([np.stack([idx[:-1].ravel(), nxt[:-1].ravel(), idx[1:].ravel()], 1),
                        np.stack([nxt[:-1].ravel(), nxt[1:].ravel(), idx[1:].ravel()], 1)])
    return V, F


def test_auto_boundary_of_a_skirt_is_its_waistband():
    B, BF = cylinder_body()
    V, F = frustum(0.155, 0.3, 0.9, 0.5)  # tight (5 mm) at the waist, flaring to the hem
    ids, _ = auto_boundary(V, F, B, BF)
    waist = np.flatnonzero(V[:, 2] > 0.899)
    assert set(waist) <= set(ids)  # the whole waist ring
    assert V[ids, 2].min() > 0.85 and len(ids) <= 3 * len(waist)  # and only a band under it
    side = B[:, 0] > 0.0  # say the +x half of the body were an arm: nothing hangs from there
    ids2, _ = auto_boundary(V, F, B, BF, avoid=side)
    assert set(ids2) < set(ids) and V[ids2, 0].max() < 0.02 and len(ids2) > 0.3 * len(ids)


def test_arm_vertices_are_the_arms(collider_body):
    from physavatar.garment.boundary import arm_vertices

    body = collider_body
    arm = arm_vertices(body)
    B = body.rest_vertices
    hands = np.abs(B[:, 0]) > 0.35  # the A-pose arms reach out past the hips
    assert arm[hands].all() and not arm[np.abs(B[:, 0]) < 0.1].any()


def test_start_repair_pushes_a_crossing_cloth_out_to_dhat_and_refuses_beyond_the_limit():
    B, BF = cylinder_body()
    V, F = frustum(0.148, 0.148, 0.8, 0.6, n_around=48)  # 2 mm inside the body
    dhat = 1e-3
    x, rep = repair_start(V, F, B, BF, dhat, limit=0.03)
    scene = ContactScene(x, F, B, BF, dhat)
    X = np.vstack([x, B])
    scene.prepare_static(X)
    assert not scene.has_intersections(X) and scene.min_distance(X) >= dhat
    assert rep["moved_vertices"] == len(V) and 0.002 < rep["max_move"] < 0.006
    V, F = frustum(0.1, 0.1, 0.8, 0.6, n_around=48)  # 5 cm inside
    with pytest.raises(PhysavatarError, match="repair limit"):
        repair_start(V, F, B, BF, dhat, limit=0.03)


def test_bad_garments_give_one_line(tmp_path):
    V = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1.0]])
    write_obj(tmp_path / "nm.obj", V, np.array([[0, 1, 2], [1, 0, 3], [0, 1, 4]]))
    with pytest.raises(PhysavatarError, match="non-manifold") as e:
        load_garment(tmp_path / "nm.obj")
    assert e.value.path == tmp_path / "nm.obj"
    B, BF = cylinder_body()
    for k in range(2):
        write_ply(tmp_path / "body" / f"{k}.ply", PlyMesh(B, BF))
    Vg, Fg = frustum(0.2, 0.3, 3.0, 2.6)  # two metres above the body
    write_obj(tmp_path / "far.obj", Vg, Fg)
    r = runner.invoke(app, ["simulate", "--collider", str(tmp_path / "body"), "--garment", str(tmp_path / "far.obj"),
                            "--out", str(tmp_path / "o"), "--no-preview"])
    assert r.exit_code == 2 and "far.obj" in r.output and "nothing holds it" in r.output
    assert "Traceback" not in r.output and len(r.output.strip().splitlines()) == 1


def two_panel_skirt(tmp_path, B):
    """A skirt of two half-panels (separate vertices at the side seams) around the hips of the body
    B [Nb, 3] (rest pose), 6 mm outside it, written as s-w.obj with a rest-shape file s-m.obj (2 %
    smaller, the second panel laid apart); returns its world vertices."""
    torso = B[np.abs(B[:, 0]) < 0.22]  # not the hands
    c = torso[(torso[:, 2] > 0.85) & (torso[:, 2] < 1.05), :2].mean(0)
    V, _ = frustum(1.0, 1.0, 1.05, 0.75, n_around=24, n_down=6)
    radius = []
    for z in np.linspace(1.05, 0.75, 7):  # each row 6 mm outside the body's widest point near its height
        near = torso[np.abs(torso[:, 2] - z) < 0.03]
        radius.append(np.linalg.norm(near[:, :2] - c, axis=1).max() + 0.006)
    radius = np.maximum.accumulate(radius)  # a skirt: never narrower below
    V[:, :2] = V[:, :2] * np.repeat(radius, 24)[:, None] + c
    halves = []
    for lo, hi in ((0, 12), (12, 24)):  # each half has its own copy of the seam columns 0/12 (and 24 = 0)
        cols = [(lo + k) % 24 for k in range(hi - lo + 1)]
        idx = np.array([[row * 24 + col for col in cols] for row in range(7)])
        Vh = V[idx.ravel()]
        a, b, cc, d = idx[:-1, :-1], idx[:-1, 1:], idx[1:, 1:], idx[1:, :-1]
        loc = {g: i for i, g in enumerate(idx.ravel())}
        Fh = np.array([[loc[x] for x in t] for t in np.concatenate([np.stack([a.ravel(), b.ravel(), cc.ravel()], 1),
                                                                    np.stack([a.ravel(), cc.ravel(), d.ravel()], 1)])])
        halves.append((Vh, Fh))
    world = np.vstack([halves[0][0], halves[1][0]])
    faces = np.vstack([halves[0][1], halves[1][1] + len(halves[0][0])])
    write_obj(tmp_path / "s-w.obj", world, faces)
    rest = world * 0.98  # 2 % smaller: the world is stretched by 1/0.98; the second panel laid apart
    rest[len(halves[0][0]):, 0] += 2.0
    write_obj(tmp_path / "s-m.obj", rest, faces)
    return world


def test_simulate_a_garment_file_on_a_motion(tmp_path):
    """`simulate --garment FILE --motion M` (--no-fit: the file is already on Anny's rest pose):
    a skirt of two half-panels (separate vertices at the side seams, a rest-shape file) around
    the hips; the seams stay shut, the boundary is chosen at the top, every frame is clean."""
    import json

    from physavatar.body import BodyModel

    world = two_panel_skirt(tmp_path, BodyModel(topology="collider").rest_vertices)
    r = runner.invoke(app, ["simulate", "--garment", str(tmp_path / "s-w.obj"), "--motion", "walk", "--no-fit",
                            "--duration", "0.12", "--out", str(tmp_path / "o"), "--no-preview"])
    assert r.exit_code == 0, r.output
    cfg = json.loads((tmp_path / "o" / "config.json").read_text())
    gi = cfg["garment_import"]
    assert gi["rest_source"] == "file" and gi["seam_pairs"] == 14 and cfg["frames_with_intersection_or_nan"] == []
    z = np.load(tmp_path / "o" / "garment_sequence.npz")
    g = load_garment(tmp_path / "s-w.obj")
    assert np.allclose(z["rest_vertices"], g.rest, atol=1e-6)
    assert max(seam_gaps(x, g.seams).max() for x in z["vertices"]) < 2e-3
    assert len(z["boundary"]) and world[:, 2].max() - g.vertices[z["boundary"], 2].min() < 0.3 * 0.3 + 1e-6
    assert np.array_equal(z["seams"], g.seams)  # the seams are stored: a reader can sew it again
    from physavatar.data.garment_sequence import GarmentSequence
    from physavatar.stages.simulate import garment_file

    part, _ = garment_file(tmp_path / "o" / "garment_sequence.npz")
    assert np.array_equal(GarmentSequence.load(tmp_path / "o").seams, g.seams) and np.array_equal(part.seams, g.seams)


def test_animate_an_avatar_in_a_garment_file(tiny_capture, tmp_path):
    """`animate --garment FILE`: the tiny avatar wears a two-panel skirt file instead of its own
    garment (--no-fit: the file is on Anny's rest pose in the avatar's shape); the sequence holds
    the avatar's body and the skirt, free of garment–body intersections, its seams shut."""
    import json

    from physavatar.body import BodyModel
    from physavatar.capture import load_capture
    from physavatar.data.animated import AnimatedSequence
    from physavatar.geometry import count_intersections
    from physavatar.stages.animate import AnimateConfig, run
    from physavatar.stages.avatar import build_avatar

    cap = load_capture(tiny_capture)
    av = build_avatar(tiny_capture, tmp_path / "avatar", material=tiny_capture / "ground_truth" / "material.json")
    body = BodyModel(av.shape, topology="collider")
    two_panel_skirt(tmp_path, body.rest_vertices)
    g = load_garment(tmp_path / "s-w.obj")
    cfg = AnimateConfig(motion="walk", duration=0.12, warmup=0.12, garment=str(tmp_path / "s-w.obj"), fit=False)
    r = run(tmp_path / "avatar", out=tmp_path / "anim", config=cfg)
    seq = AnimatedSequence.load(tmp_path / "anim")
    nb = int((cap.template.labels == 0).sum())
    assert seq.vertices.shape[1] == nb + len(g.vertices) and (seq.labels[nb:] > 0).all() and (seq.labels[:nb] == 0).all()
    assert seq.face_uvs is None or len(seq.face_uvs) == len(seq.faces)
    meta = json.loads((tmp_path / "anim" / "sequence.json").read_text())
    assert meta["garment_import"]["seam_pairs"] == len(g.seams)
    assert r.stats["warmup_frames"] == 0  # walk starts in the zero pose the garment is on (not the capture's)
    gf = seq.faces[(seq.faces >= nb).all(1)] - nb
    assert np.array_equal(np.sort(gf, axis=1), np.sort(g.faces, axis=1))
    from physavatar.body.load import load_motion

    m = load_motion("walk", av.fps, 0.12)
    posed = body.pose(m.rotations, m.root_translation).vertices
    for t in range(len(seq.vertices)):
        x = seq.vertices[t, nb:]
        assert count_intersections(x, g.faces, posed[t], body.faces) == 0
        assert seam_gaps(x, g.seams).max() < 2e-3


# -- fitting a garment with sleeves: the limbs posed through its openings ----------------------


def tube_shirt(shoulder_l, shoulder_r, theta_deg, spacing=0.012, sleeve=0.3, r_arm=0.08, r_torso=0.22, bottom=0.85):
    """A shirt (marching cubes, scikit-image, of a solid torso with a sloped top and two sleeve
    cylinders, then the caps cut open): sleeves from the shoulder points going out and down by
    ``theta_deg`` below horizontal, open at the neck, the hem and the cuffs. (V, F, d_l, d_r)."""
    import scipy.sparse as sp
    from scipy.sparse.csgraph import connected_components
    from skimage.measure import marching_cubes

    top = shoulder_l[2] + 0.12
    d_l = np.array([np.cos(np.radians(theta_deg)), 0.0, -np.sin(np.radians(theta_deg))])
    d_r = d_l * [-1, 1, 1]
    lo, hi = np.array([-0.75, -0.3, bottom - 0.1]), np.array([0.75, 0.3, top + 0.1])
    X = np.stack(np.meshgrid(*[np.arange(a, b, spacing) for a, b in zip(lo, hi)], indexing="ij"), -1)
    roof = top - 0.35 * np.abs(X[..., 0])
    f = np.maximum(np.hypot(X[..., 0], X[..., 1]) - r_torso, np.maximum(X[..., 2] - roof, bottom - X[..., 2]))
    for J, d in ((shoulder_l, d_l), (shoulder_r, d_r)):
        t = (X - J) @ d
        rr = np.linalg.norm(X - J - t[..., None] * d, axis=-1)
        f = np.minimum(f, np.maximum(rr - r_arm, np.maximum(t - sleeve, -t)))
    V, F, _, _ = marching_cubes(f, 0.0, spacing=(spacing,) * 3)
    V += lo
    C = V[F].mean(1)
    eps = 0.6 * spacing
    cut = ((C[:, 2] > top - 0.35 * 0.09 - eps) & (np.hypot(C[:, 0], C[:, 1]) < 0.09)) | (C[:, 2] < bottom + eps)
    for J, d in ((shoulder_l, d_l), (shoulder_r, d_r)):
        cut |= (C - J) @ d > sleeve - eps
    F = F[~cut][:, ::-1]
    A = sp.coo_matrix((np.ones(3 * len(F)), (F.ravel(), F[:, [1, 2, 0]].ravel())), shape=(len(V), len(V)))
    lab = connected_components(A, directed=False)[1]
    F = F[lab[F[:, 0]] == np.bincount(lab[F[:, 0]]).argmax()]  # the shirt, not crumbs of a cut cap
    return V, F, d_l, d_r


@pytest.fixture(scope="module")
def collider_body():
    from physavatar.body import BodyModel

    return BodyModel(topology="collider")


def _shoulders(body):
    n = list(body.bone_names)
    return body.rest_joints[n.index("upperarm01.L")], body.rest_joints[n.index("upperarm01.R")]


@pytest.mark.parametrize("theta", [20.0, -25.0])
def test_sleeve_openings_give_the_arm_pose(collider_body, theta):
    """The openings of a synthetic shirt are found and named, and the solved pose puts each upper
    arm along its sleeve's known axis (and the forearm in line: the elbow straightened)."""
    from physavatar.garment.openings import find_openings, lateral_axis, limb_pose

    body = collider_body
    V, F, d_l, d_r = tube_shirt(*_shoulders(body), theta)
    ops = find_openings(V, F)
    assert sorted(o.kind for o in ops) == ["arm", "arm", "hem", "neck"]
    assert abs(abs(lateral_axis(ops)[0]) - 1.0) < 1e-3
    rots, aims = limb_pose(body, ops)
    J = body.pose(rots[None], np.zeros((1, 3))).joints[0]
    n = list(body.bone_names)
    for side, d in (("L", d_l), ("R", d_r)):
        s = J[n.index(f"upperarm01.{side}")]
        for end in ("lowerarm01", "wrist"):
            u = J[n.index(f"{end}.{side}")] - s
            assert np.degrees(np.arccos(np.clip(u @ d / np.linalg.norm(u), -1, 1))) < 2.0, (side, end)
        assert aims[f"upperarm01.{side}"]["towards"] == "centre"
    assert not np.any(rots[[n.index("upperleg01.L"), n.index("upperleg01.R")]])  # no leg openings


def test_a_shirt_whose_sleeves_point_up_fits_with_the_arms_posed_through_them(collider_body, tmp_path):
    """A coarse shirt with sleeves 25° above horizontal, placed on Anny's shoulders: with the arm
    raises alone (up to 50° from the A-pose) the arms cross the sleeves' walls however thin the
    body is shrunk; posed through the openings, the body clears the shirt shrunk to 0.8 of its
    girth, grows inside it, turns its arms back down, and the shirt ends clear of the rest body
    (ipctk), its strain small and its cuffs around the arms."""
    from physavatar.garment.fit import Alignment, _start_girth, arms_raised
    from physavatar.garment.openings import find_openings, limb_pose
    from physavatar.garment_sim import fit_on_body, rest_strain
    from physavatar.geometry import MeshQuery

    body = collider_body
    V, F, _, _ = tube_shirt(*_shoulders(body), -25.0, spacing=0.04)
    write_obj(tmp_path / "shirt.obj", V, F)
    gm = load_garment(tmp_path / "shirt.obj")  # (drops marching cubes' slivers)
    V, F = gm.vertices, gm.faces
    rots, aims = limb_pose(body, find_openings(V, F))
    B = body.pose(rots[None], np.zeros((1, 3))).vertices[0]
    al = Alignment(V, 0.0, np.zeros(3), 0.0, B, 0.0, 0.0, 0.0, 1.0, F, rots, aims)
    alpha, left = _start_girth(body, V, F, rots, 1e-3, 0.3)
    assert alpha >= 0.8 and left == 0
    for raise_deg in (0.0, 20.0, 35.0, 50.0):  # (a shrunk arm still crosses the sleeve's wall)
        assert _start_girth(body, V, F, arms_raised(body, raise_deg)[0], 1e-3, 0.3)[1] > 0
    mat = preset("cotton")
    part, rep = fit_on_body(gm, body, mat, SimSettings(integrator=mat.integrator), frames=3, pose_frames=3,
                            hold=1, alignment=al)
    x = part.vertices
    scene = ContactScene(x, F, body.rest_vertices, body.faces, 1e-3)
    assert not scene.has_intersections(np.vstack([x, body.rest_vertices]))
    assert rep["strain_mean"] < 0.05
    n = list(body.bone_names)
    for o in (o for o in find_openings(x, F) if o.kind == "arm"):  # each cuff around its (rest) upper arm
        side = "L" if o.centre[0] > 0 else "R"
        a, e = body.rest_joints[n.index(f"upperarm01.{side}")], body.rest_joints[n.index(f"lowerarm01.{side}")]
        t = np.clip((o.centre - a) @ (e - a) / ((e - a) @ (e - a)), 0, 1)
        assert np.linalg.norm(o.centre - (a + t * (e - a))) < o.radius
    assert MeshQuery(body.rest_vertices, body.faces).signed_distance(x, max_dist=0.1)[0].min() > 0


def test_start_repair_untangles_a_slight_self_intersection():
    """Two parallel panels 4 mm apart, one vertex of the upper one poked 3 mm through the lower:
    the cloth crosses itself (ipctk's edge–triangle test); the repair pulls the vertex back over
    the lower panel and nothing else moves far; a far body changes nothing else."""
    from physavatar.sim.start import self_crossings, untangle

    Va, Fa = panel(0.0, 0.2, 0.2, 8)
    Vb, Fb = panel(0.0, 0.2, 0.2, 8, y=0.004)
    V = np.vstack([Va, Vb])
    F = np.vstack([Fa, Fb + len(Va)])
    poked = len(Va) + 4 * 9 + 4  # the middle of the upper panel
    V[poked, 1] = -0.003
    assert len(self_crossings(V, F)) > 0
    x, rep = untangle(V, F)
    assert rep["self_crossings_before"] > 0 and rep["self_crossings_after"] == 0 and len(self_crossings(x, F)) == 0
    assert x[poked, 1] > 0 and np.abs(x[: len(Va)] - Va).max() < 0.004  # back over the lower panel
    B, BF = cylinder_body(0.05, 0.1)
    xr, rep = repair_start(V, F, B + [5.0, 0, 0], BF, 1e-3)
    assert rep["self_crossings"]["before"] > 0 and rep["self_crossings"]["after"] == 0
    assert np.allclose(xr, x)


def folding_roof(frames=11, theta_max=25.0, w=0.03, a=0.005, o=0.001):
    """A body that bends at an edge (a shoulder as the arm swings, in miniature): two 6 × 3 cm
    faces meeting at a ridge along x, folding down by θ = 0 … ``theta_max`` degrees each, and a
    3 × 2-vertex cloth patch ``o`` above it whose middle column is an edge across the ridge
    (its ends ``a`` from the ridge). Returns (bodies [T, 6, 3], body faces, cloth [6, 3],
    cloth faces, boundary = the middle column, θ [T] in radians)."""
    th = np.radians(np.linspace(0.0, theta_max, frames))
    bodies = np.stack([np.array([[x, s * w * np.cos(t), -abs(s) * w * np.sin(t)] for s in (-1, 0, 1) for x in (-0.03, 0.03)])
                       for t in th])
    BF = np.array([[0, 1, 3], [0, 3, 2], [2, 3, 5], [2, 5, 4]])  # normals +z
    cloth = np.array([[x, y, o] for y in (-a, a) for x in (-a, 0.0, a)])
    F = np.array([[0, 1, 4], [0, 4, 3], [1, 2, 5], [1, 5, 4]])
    return bodies, BF, cloth, F, np.array([1, 4]), th


def test_boundary_targets_are_kept_clear_of_a_bending_body():
    """Each boundary vertex rides its own body triangle; the straight edge between two of them
    sinks through the ridge once o cos θ < a sin θ (θ > 11.3° here): the prescribed motion
    itself crosses the body (the Berkeley t-shirt's left shoulder on walk and dance). keep_clear
    lifts the targets to the floor (the start distance, below 0.5 mm) at every frame and leaves
    frame 0 and the clear frames as they were."""
    from physavatar.garment import attachment_positions, keep_clear, make_attachment
    from physavatar.garment_sim import GarmentPart, simulate_on_body

    bodies, BF, cloth, F, bnd, th = folding_roof()
    att = make_attachment(cloth[bnd], bnd, bodies[0], BF, "sequence")
    raw = attachment_positions(att, bodies)
    mid = 0.5 * (raw[:, 0] + raw[:, 1])
    np.testing.assert_allclose(mid[:, 2], 0.001 * np.cos(th) - 0.005 * np.sin(th), atol=1e-12)  # analytic
    lifted, rep = keep_clear(att, raw, F, bodies, BF, 0.5e-3)
    crossing = np.flatnonzero(mid[:, 2] < 0)
    assert len(crossing) >= 5  # the scene does cross without the lift
    np.testing.assert_array_equal(lifted[0], raw[0])
    assert rep["floor_m"] == 0.5e-3 and not rep["failed_frames"]
    for t in range(len(th)):
        gap = np.sqrt(ipctk.edge_edge_distance(lifted[t, 0], lifted[t, 1], bodies[t, 2], bodies[t, 3]))
        if 0.001 * np.cos(th[t]) - 0.005 * np.sin(th[t]) >= 0.5e-3:  # clear of the floor: untouched
            np.testing.assert_array_equal(lifted[t], raw[t])
        else:
            assert 0.5e-3 * (1 - 1e-6) <= gap < 1.0e-3, (t, gap)
    # and the simulation (both cloth columns beside the boundary free) is clean at every frame
    part = GarmentPart(np.arange(6), cloth, F, bnd)
    mat = preset("cotton")
    X = simulate_on_body(part, bodies, BF, mat, 25.0, settings=SimSettings(integrator=mat.integrator, gravity=(0, 0, 0)))
    scene = ContactScene(cloth, F, bodies[0], BF, 1e-3)
    bad = [t for t in range(len(X)) if not np.isfinite(X[t]).all() or scene.has_intersections(np.vstack([X[t], bodies[t]]))]
    assert not bad


def test_sewn_boundary_vertices_ride_one_body_point():
    """Two boundary vertices sewn together at a body edge (the dress's armhole seam on the
    shoulder), attached each to its own closest triangle, are carried apart as the faces fold:
    o above the ridge, along each face's normal, they part by 2 o sin θ and no stitch can pull
    them back (both prescribed). garment_sim.sewn_points attaches them at one point."""
    from physavatar.garment import attachment_positions, make_attachment
    from physavatar.garment_sim import sewn_points

    bodies, BF, _, _, _, th = folding_roof()
    o = 0.002
    V = np.array([[0.0, -1e-6, o], [0.0, 1e-6, o], [0.01, 0.01, o]])  # a seam pair astride the ridge, one more
    bnd, seams = np.array([0, 1, 2]), np.array([[0, 1]])
    apart = attachment_positions(make_attachment(V[bnd], bnd, bodies[0], BF, "s"), bodies)
    np.testing.assert_allclose(np.linalg.norm(apart[:, 0] - apart[:, 1], axis=1), 2 * o * np.sin(th), atol=1e-5)
    pts = sewn_points(V, bnd, seams)
    np.testing.assert_allclose(pts, [[0, 0, o], [0, 0, o], V[2]], atol=1e-15)
    one = attachment_positions(make_attachment(pts, bnd, bodies[0], BF, "s"), bodies)
    np.testing.assert_array_equal(one[:, 0], one[:, 1])
    np.testing.assert_array_equal(one[:, 2], apart[:, 2])


def test_sewn_boundary_vertices_are_lifted_together():
    """A boundary vertex sewn to one of a sinking boundary edge's ends (a second panel meeting
    it at a seam, its own edges all to free cloth) shares that end's attachment point
    (sewn_points) and must share its lift too: lifted alone, the end leaves its partner on the
    body and the seam opens by the lift (the skirt's and dress's seams on the CMU clips opened by
    exactly their largest lift, 0.8-2.0 mm)."""
    from physavatar.garment import attachment_positions, keep_clear, make_attachment
    from physavatar.garment_sim import sewn_points

    bodies, BF, cloth, F, bnd, th = folding_roof()
    a, o = 0.005, 0.001
    V = np.vstack([cloth, [[0.0, a, o], [0.0, 3 * a, o], [a, 3 * a, o]]])  # 6: sewn to 4; 7, 8 free
    F2 = np.vstack([F, [[6, 8, 7]]])
    bnd2, seams = np.r_[bnd, 6], np.array([[4, 6]])
    att = make_attachment(sewn_points(V, bnd2, seams), bnd2, bodies[0], BF, "sequence")
    raw = attachment_positions(att, bodies)
    lifted, rep = keep_clear(att, raw, F2, bodies, BF, 0.5e-3)
    np.testing.assert_array_equal(raw[:, 1], raw[:, 2])  # one attachment point
    assert rep["max_lift_m"] > 0.3e-3 and not rep["failed_frames"]
    moved = np.linalg.norm(lifted[:, 1] - raw[:, 1], axis=1)
    assert (moved > 0.3e-3).sum() >= 5
    np.testing.assert_array_equal(lifted[:, 1], lifted[:, 2])  # the seam stays closed


def test_keep_clear_recovers_after_a_failed_frame():
    """A failed frame leaves the boundary closer to the body than half the floor; the next
    frame's path must then be allowed to start there (half its own start distance), or the CCD
    stops at once whatever the lift, the frame fails too and the lift grows frame after frame
    (the t-shirt's lift on 131_01 grew to 7.67 mm). Scene: the folding roof's cloth patch o = 1 mm
    over a flat body sheet (normals +z), its boundary edge along y at x = 0, and a tall body wall
    (an arm at the side) that presses to g = 0.1 mm beside the edge at odd frames and is 3 cm
    away at even ones. A lift along the sheet's normal cannot leave a wall beside it: each
    pressed frame fails with exactly ``rounds`` × 1.25 (floor − g) of lift, and its edge ends g
    from the wall (< floor / 2). Each relief frame's own targets pass from there (half the start
    distance, g / 2): they are kept bit for bit and the lift drops back to 0, so it never exceeds
    one pressed frame's (the code before 079e741 failed every frame from 1 on, its lift growing
    by 4 mm a frame to 24 mm). Every lifted step is free of the body per ipctk's CCD."""
    from physavatar.garment import attachment_positions, keep_clear, make_attachment

    a, o, g, floor, rounds = 0.005, 0.001, 0.1e-3, 0.5e-3, 8
    sheet = np.array([[x, y, 0.0] for x in (-0.03, 0.03) for y in (-0.03, 0.03)])
    wall = np.array([[0.0, y, z] for y in (-0.03, 0.03) for z in (-0.05, 0.05)])
    xw = np.array([0.03, g, 0.03, g, 0.03, g, 0.03])  # the wall's x at each frame
    bodies = np.stack([np.vstack([sheet, wall + [x, 0, 0]]) for x in xw])
    BF = np.array([[0, 2, 3], [0, 3, 1], [4, 5, 7], [4, 7, 6]])  # the sheet (normal +z), the wall
    cloth = np.array([[x, y, o] for y in (-a, a) for x in (-a, 0.0, a)])
    F = np.array([[0, 1, 4], [0, 4, 3], [1, 2, 5], [1, 5, 4]])
    bnd = np.array([1, 4])  # the edge (0, ±a, o)
    att = make_attachment(cloth[bnd], bnd, bodies[0], BF, "sequence")
    assert (np.asarray(att.triangles) < 4).all()  # riding the sheet's triangles: lifted along +z
    raw = attachment_positions(att, bodies)
    np.testing.assert_allclose(raw, np.broadcast_to(cloth[bnd], raw.shape), atol=1e-15)  # the sheet is still
    lifted, rep = keep_clear(att, raw, F, bodies, BF, floor, rounds=rounds)
    pressed, relief = [1, 3, 5], [2, 4, 6]
    assert rep["floor_m"] == floor and rep["failed_frames"] == pressed
    one = rounds * 1.25 * (floor - g)  # 4 mm: a pressed frame's lift (the shortfall g short of the floor, each round)
    assert abs(rep["max_lift_m"] - one) < 1e-9, rep
    for t in pressed:  # failed, lifted along +z only: the edge ends g from the wall, inside half the floor
        np.testing.assert_allclose(lifted[t] - raw[t], [[0, 0, one]] * 2, atol=1e-9)
        assert np.allclose(xw[t] - lifted[t, :, 0], g) and lifted[t, :, 2].max() < 0.05 and g < 0.5 * floor
    for t in relief:  # a path from g to 3 cm off the wall needs no lift: kept bit for bit, the lift dropped
        np.testing.assert_array_equal(lifted[t], raw[t])
    # every lifted step, pressed ones included, is free of the body per ipctk's CCD; the relief
    # steps keep at least half their start distance g (the path keep_clear now asks for)
    E = np.vstack([[[0, 1]], ipctk.edges(BF.astype(np.int32)) + 2])
    mesh = ipctk.CollisionMesh(np.vstack([lifted[0], bodies[0]]), E, (BF + 2).astype(np.int32))
    mesh.can_collide = ipctk.make_vertex_patches_filter(np.r_[0, 0, np.ones(len(bodies[0]))].astype(np.int32))
    ccd = ipctk.TightInclusionCCD(1e-6, 1_000_000)
    for t in range(1, len(xw)):
        V0, V1 = np.vstack([lifted[t - 1], bodies[t - 1]]), np.vstack([lifted[t], bodies[t]])
        assert ipctk.is_step_collision_free(mesh, V0, V1, 0.5 * g if t in relief else 0.0, narrow_phase_ccd=ccd), t
