"""The body, and a garment built on it, are the same bit for bit whatever torch's thread count
(Anny's forward pass runs on one thread: physavatar.body.model.one_thread). On two threads a
5-cm dress used to get 557 vertices where one thread gave 556, so a capture made on another
machine, or a resume on one, was another garment."""

import numpy as np
import torch

from physavatar.body.model import BodyModel, BodyShape, _floor_offset
from physavatar.garment import make_garment


def _build(threads: int):
    before = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        _floor_offset.cache_clear()
        body = BodyModel(BodyShape(weight=0.7, height=0.35))
        rot, tr = body.rest_pose(6)
        rot = rot + 0.05 * np.random.default_rng(0).standard_normal(rot.shape)
        posed = body.pose(rot, tr)
        dress = make_garment("dress", body, edge_length=0.05)
        return body.rest_vertices, posed.vertices, posed.bone_transforms, dress.vertices, dress.faces
    finally:
        torch.set_num_threads(before)


def test_body_and_garment_do_not_depend_on_the_thread_count():
    one, two = _build(1), _build(2)
    for a, b in zip(one, two):
        assert a.shape == b.shape
        assert np.array_equal(a, b)
