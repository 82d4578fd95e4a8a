"""A small, valid capture folder built without the renderer, for format and validation tests.

Geometry: an icosphere "body" (label 0) and an open cylinder "skirt" around it (label 1) whose
top ring is the boundary. Images are random noise of the cameras' size.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import trimesh

from physavatar.body.model import BodyShape
from physavatar.camera import ring_rig
from physavatar.capture_checks import silhouette
from physavatar.capture import BodyPoses, Template, frame_name, save_cameras, save_capture_meta, save_png

BONES = ["root", "spine05", "upperleg01.L"]


def cylinder(radius=0.3, height=0.4, z0=0.6, n_around=16, n_up=4):
    th = np.linspace(0, 2 * np.pi, n_around, endpoint=False)
    zs = np.linspace(z0, z0 + height, n_up + 1)
    V = np.array([[radius * np.cos(t), radius * np.sin(t), z] for z in zs for t in th])
    F = []
    for i in range(n_up):
        for j in range(n_around):
            a, b = i * n_around + j, i * n_around + (j + 1) % n_around
            c, d = a + n_around, b + n_around
            F += [[a, b, d], [a, d, c]]
    return V, np.array(F)


def make_template():
    s = trimesh.creation.icosphere(subdivisions=2, radius=0.2)
    bv = np.asarray(s.vertices) + [0, 0, 0.8]
    bf = np.asarray(s.faces)
    gv, gf = cylinder()
    V = np.concatenate([bv, gv])
    F = np.concatenate([bf, gf + len(bv)])
    labels = np.concatenate([np.zeros(len(bv), int), np.ones(len(gv), int)])
    boundary = np.zeros(len(V), bool)
    top = gv[:, 2] > gv[:, 2].max() - 1e-9
    boundary[len(bv):][top] = True
    uvs = np.random.default_rng(0).random((len(F), 3, 2))
    return Template(V, F, labels, boundary, uvs)


def make_capture(root: Path, n_cams: int = 2, n_frames: int = 3, size=(32, 24), masks: bool = True) -> Path:
    root = Path(root)
    rng = np.random.default_rng(0)
    cams = ring_rig(n_cams, 2.5, 1.0, (0, 0, 0.8), size[0], size[1], 40.0)
    frames = list(range(n_frames))
    save_capture_meta(root, fps=25.0, frames=frames, extra={"garment_source": "test"})
    save_cameras(root, cams)
    template = make_template()
    for c in cams:
        # the masks are the template's silhouette (inspect compares them with its projection)
        sil = silhouette(c, template.vertices, template.faces)
        for f in frames:
            save_png(root / "images" / c.name / f"{frame_name(f)}.png", rng.random((size[1], size[0], 3)))
            if masks:
                save_png(root / "masks" / c.name / f"{frame_name(f)}.png", sil)
    BodyPoses(BodyShape(), BONES, np.zeros((n_frames, len(BONES), 3)), np.zeros((n_frames, 3))).save(root / "body.npz")
    template.save(root / "template" / "mesh.ply")
    return root
