"""PLY reading/writing against trimesh (an independent reader) and atomic writes."""

import numpy as np
import pytest
import trimesh

from physavatar.errors import PhysavatarError
from physavatar.files import PlyMesh, atomic_path, read_ply, write_ply


def test_ply_roundtrip_with_properties(tmp_path):
    rng = np.random.default_rng(1)
    V = rng.random((10, 3))
    F = rng.integers(0, 10, (7, 3))
    m = PlyMesh(V, F, {"label": rng.integers(0, 3, 10).astype(np.uint8), "boundary": np.ones(10, np.uint8)},
                rng.random((7, 3, 2)))
    write_ply(tmp_path / "a.ply", m)
    r = read_ply(tmp_path / "a.ply")
    assert np.allclose(r.vertices, V, atol=1e-6)  # float32 on disk
    assert (r.faces == F).all()
    assert (r.vertex_data["label"] == m.vertex_data["label"]).all()
    assert np.allclose(r.face_uvs, m.face_uvs, atol=1e-6)
    # an independent reader sees the same geometry
    t = trimesh.load(tmp_path / "a.ply", process=False)
    # (trimesh splits vertices at UV seams, so compare the triangles' corner positions)
    assert np.allclose(np.asarray(t.vertices)[np.asarray(t.faces)], V[F], atol=1e-6)


def test_ply_reads_ascii_and_quads(tmp_path):
    text = "\n".join([
        "ply", "format ascii 1.0", "element vertex 4", "property float x", "property float y",
        "property float z", "property uchar label", "element face 1", "property list uchar int vertex_indices",
        "end_header", "0 0 0 1", "1 0 0 1", "1 1 0 2", "0 1 0 2", "4 0 1 2 3", ""])
    (tmp_path / "q.ply").write_text(text)
    r = read_ply(tmp_path / "q.ply")
    assert r.faces.tolist() == [[0, 1, 2], [0, 2, 3]]
    assert r.vertex_data["label"].tolist() == [1, 1, 2, 2]


def test_trimesh_written_ply_is_read(tmp_path):
    s = trimesh.creation.icosphere(1)
    s.export(tmp_path / "s.ply")
    r = read_ply(tmp_path / "s.ply")
    assert np.allclose(r.vertices, s.vertices, atol=1e-6) and (r.faces == s.faces).all()


def test_bad_ply_names_the_file(tmp_path):
    (tmp_path / "x.ply").write_bytes(b"not a ply at all")
    with pytest.raises(PhysavatarError, match="x.ply"):
        read_ply(tmp_path / "x.ply")


def test_atomic_write_leaves_old_file_on_failure(tmp_path):
    p = tmp_path / "out.txt"
    p.write_text("old")
    with pytest.raises(RuntimeError):
        with atomic_path(p) as tmp:
            tmp.write_text("half")
            raise RuntimeError("interrupted")
    assert p.read_text() == "old"
    assert [q.name for q in tmp_path.iterdir()] == ["out.txt"]


def test_content_key_follows_content_not_names_or_times(tmp_path):
    """files.content_key: what resumes compare (session 27). Bytes count, modification times do not."""
    import os

    from physavatar.files import content_key

    f = tmp_path / "a.bin"
    f.write_bytes(b"one")
    k = content_key(f, np.arange(3), x=1)
    os.utime(f, (1, 1))
    assert content_key(f, np.arange(3), x=1) == k                    # touched: the same
    assert content_key(f, np.arange(3), x=2) != k                    # settings
    assert content_key(f, np.arange(3.0), x=1) != k                  # dtype
    assert content_key(f, np.arange(4), x=1) != k                    # array bytes
    f.write_bytes(b"two")
    os.utime(f, (1, 1))
    assert content_key(f, np.arange(3), x=1) != k                    # same size and time, other bytes
    assert content_key(tmp_path / "missing") != content_key(tmp_path / "missing2", tmp_path / "missing")
    d = tmp_path / "d"
    d.mkdir()
    (d / "x").write_bytes(b"1")
    kd = content_key(d)
    (d / "x").rename(d / "y")
    assert content_key(d) != kd                                      # a folder: names count
