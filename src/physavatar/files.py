"""Atomic file writing and the PLY mesh format used by capture templates and tracked meshes.

Every output is written to a temporary name in the same folder and renamed into place, so an
interrupted run never leaves a half-written file under the final name.

PLY: binary little-endian on write; ascii and binary (either endianness) on read. Vertex
properties beyond x, y, z (``label``, ``boundary``, colours ...) become named arrays; per-corner
UVs use the MeshLab convention, a face property ``list uchar float texcoord`` with 6 floats per
triangle, which MeshLab and Blender read.
"""

from __future__ import annotations

import contextlib
import json
import os
import tempfile
from pathlib import Path
from typing import Iterator

import numpy as np

from .errors import PhysavatarError

_UMASK = os.umask(0)
os.umask(_UMASK)

# -- atomic writes -------------------------------------------------------------------------------


@contextlib.contextmanager
def atomic_path(path: str | Path) -> Iterator[Path]:
    """Yield a temporary path next to ``path``; on success rename it to ``path``.

    The suffix is kept so libraries that infer the format from the name still work.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=path.suffix, dir=path.parent)
    os.close(fd)
    tmp = Path(tmp)
    os.chmod(tmp, 0o666 & ~_UMASK)  # mkstemp makes 0600; outputs get the usual permissions
    try:
        yield tmp
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()


def write_bytes_atomic(path: str | Path, data: bytes) -> None:
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)


def write_text_atomic(path: str | Path, text: str) -> None:
    write_bytes_atomic(path, text.encode("utf-8"))


def write_json_atomic(path: str | Path, obj) -> None:
    write_text_atomic(path, json.dumps(obj, indent=2, sort_keys=False) + "\n")


def save_npz_atomic(path: str | Path, **arrays) -> None:
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            np.savez_compressed(f, **arrays)


def read_json(path: str | Path) -> dict:
    path = Path(path)
    if not path.is_file():
        raise PhysavatarError(path, "file not found")
    try:
        return json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise PhysavatarError(path, f"not valid JSON ({e})") from None


def load_npz(path: str | Path, mapped: bool = False) -> dict[str, np.ndarray]:
    """The arrays of an .npz file. ``mapped``: arrays over 1 MiB are decompressed in chunks into
    unlinked temporary files and returned as read-only memory maps, so a long sequence costs disk
    and page cache, not resident memory (the viewer reads one frame at a time)."""
    path = Path(path)
    if not path.is_file():
        raise PhysavatarError(path, "file not found")
    try:
        if mapped:
            return _map_npz(path)
        with np.load(path, allow_pickle=False) as z:
            return {k: z[k] for k in z.files}
    except Exception as e:  # zipfile / pickle / format errors all mean "not a usable npz"
        raise PhysavatarError(path, f"not a readable .npz file ({type(e).__name__}: {e})") from None


def _map_npz(path: Path, small: int = 1 << 20) -> dict[str, np.ndarray]:
    import shutil
    import zipfile

    fmt = np.lib.format
    out = {}
    with zipfile.ZipFile(path) as zf:
        for name in zf.namelist():
            with zf.open(name) as f:
                version = fmt.read_magic(f)
                read_header = fmt.read_array_header_1_0 if version == (1, 0) else fmt.read_array_header_2_0
                shape, fortran, dtype = read_header(f)
                if dtype.hasobject:
                    raise ValueError(f"{name} holds Python objects")
                order = "F" if fortran else "C"
                nbytes = int(np.prod(shape)) * dtype.itemsize
                if nbytes <= small:
                    arr = np.frombuffer(f.read(nbytes), dtype).reshape(shape, order=order).copy()
                else:
                    tmp = tempfile.TemporaryFile(prefix="physavatar-npz-")
                    shutil.copyfileobj(f, tmp, 1 << 22)
                    tmp.flush()
                    if tmp.tell() != nbytes:
                        raise ValueError(f"{name} is truncated")
                    arr = np.memmap(tmp, dtype, "r", shape=shape, order=order)
                    tmp.close()  # the map keeps the data; the file was never linked
            out[name[:-4] if name.endswith(".npy") else name] = arr
    return out


# -- content keys --------------------------------------------------------------------------------


def content_key(*parts, **meta) -> str:
    """A hex digest of what a result is made from, for a resume or cache to compare: arrays
    (dtype, shape and bytes), files (their bytes; a folder: each file's relative path and bytes,
    in sorted order; a missing path counts as missing), strings (e.g. an earlier key) and
    JSON-able settings ``meta``. Equal keys: the same data, whatever the files' names or times
    (a modification time is not content). SHA-256 (arrays and settings hashed as
    data.sim_frames.fingerprint hashed them before session 27, so a simulation's frames written
    then still resume), files read in 1 MiB blocks."""
    import hashlib

    h = hashlib.sha256()
    for p in parts:
        if isinstance(p, Path):
            _hash_path(h, p)
        elif isinstance(p, str):
            h.update(b"s" + p.encode() + b"\0")
        else:
            a = np.ascontiguousarray(p)
            h.update(f"{a.dtype.str}{a.shape}".encode())
            h.update(a.tobytes())
    h.update(json.dumps(meta, sort_keys=True, default=str).encode())
    return h.hexdigest()[:32]


def _hash_path(h, path: Path) -> None:
    if path.is_dir():
        files = sorted(q for q in path.rglob("*") if q.is_file())
        h.update(f"d{len(files)}".encode())
        for q in files:
            h.update(str(q.relative_to(path)).encode() + b"\0")
            _hash_path(h, q)
    elif path.is_file():
        h.update(f"f{path.stat().st_size}".encode())
        with open(path, "rb") as f:
            for block in iter(lambda: f.read(1 << 20), b""):
                h.update(block)
    else:
        h.update(b"m")


# -- PLY -----------------------------------------------------------------------------------------

_PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1",
    "short": "i2", "int16": "i2", "ushort": "u2", "uint16": "u2",
    "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}
_NP_TO_PLY = {"i1": "char", "u1": "uchar", "i2": "short", "u2": "ushort", "i4": "int",
              "u4": "uint", "f4": "float", "f8": "double"}


class PlyMesh:
    """A triangle mesh read from or written to PLY.

    Attributes:
        vertices: [V, 3] float64.
        faces: [F, 3] int64.
        vertex_data: extra per-vertex arrays by property name, each [V].
        face_uvs: [F, 3, 2] per-corner texture coordinates, or None.
    """

    def __init__(self, vertices, faces, vertex_data=None, face_uvs=None):
        self.vertices = np.asarray(vertices, dtype=np.float64).reshape(-1, 3)
        self.faces = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
        self.vertex_data = dict(vertex_data or {})
        self.face_uvs = None if face_uvs is None else np.asarray(face_uvs, np.float64).reshape(-1, 3, 2)


def write_ply(path: str | Path, mesh: PlyMesh) -> None:
    """Write ``mesh`` as binary little-endian PLY, atomically."""
    V, F = len(mesh.vertices), len(mesh.faces)
    vfields = [("x", "<f4"), ("y", "<f4"), ("z", "<f4")]
    for name, arr in mesh.vertex_data.items():
        arr = np.asarray(arr)
        if arr.shape != (V,):
            raise ValueError(f"vertex property {name!r} has shape {arr.shape}, expected ({V},)")
        vfields.append((name, "<" + arr.dtype.str[1:] if arr.dtype.itemsize > 1 else arr.dtype.str))
    vrec = np.empty(V, dtype=vfields)
    vrec["x"], vrec["y"], vrec["z"] = mesh.vertices.T
    for name, arr in mesh.vertex_data.items():
        vrec[name] = arr
    header = ["ply", "format binary_little_endian 1.0", "comment written by physavatar",
              f"element vertex {V}"]
    for name, dt in vfields:
        header.append(f"property {_NP_TO_PLY[np.dtype(dt).str[1:]]} {name}")
    header.append(f"element face {F}")
    header.append("property list uchar int vertex_indices")
    ffields = [("n", "u1"), ("idx", "<i4", (3,))]
    if mesh.face_uvs is not None:
        header.append("property list uchar float texcoord")
        ffields += [("m", "u1"), ("uv", "<f4", (6,))]
    header.append("end_header")
    frec = np.empty(F, dtype=ffields)
    frec["n"] = 3
    frec["idx"] = mesh.faces
    if mesh.face_uvs is not None:
        frec["m"] = 6
        frec["uv"] = mesh.face_uvs.reshape(F, 6)
    data = ("\n".join(header) + "\n").encode("ascii") + vrec.tobytes() + frec.tobytes()
    write_bytes_atomic(path, data)


def read_ply(path: str | Path) -> PlyMesh:
    """Read a triangle-mesh PLY (ascii or binary). Raises PhysavatarError naming the file."""
    path = Path(path)
    if not path.is_file():
        raise PhysavatarError(path, "file not found")
    raw = path.read_bytes()
    try:
        return _parse_ply(raw)
    except PhysavatarError:
        raise
    except Exception as e:
        raise PhysavatarError(path, f"not a readable PLY mesh ({type(e).__name__}: {e})") from None


def _parse_ply(raw: bytes) -> PlyMesh:
    end = raw.find(b"end_header")
    if not raw.startswith(b"ply") or end < 0:
        raise ValueError("missing 'ply' magic or 'end_header'")
    nl = raw.index(b"\n", end)
    lines = raw[:end].decode("ascii", errors="replace").splitlines()
    body = raw[nl + 1:]
    fmt = None
    elements: list[tuple[str, int, list]] = []
    for line in lines:
        tok = line.split()
        if not tok:
            continue
        if tok[0] == "format":
            fmt = tok[1]
        elif tok[0] == "element":
            elements.append((tok[1], int(tok[2]), []))
        elif tok[0] == "property":
            if tok[1] == "list":
                elements[-1][2].append((tok[4], ("list", tok[2], tok[3])))
            else:
                elements[-1][2].append((tok[2], tok[1]))
    if fmt not in ("ascii", "binary_little_endian", "binary_big_endian"):
        raise ValueError(f"unknown PLY format {fmt!r}")
    data: dict[str, dict[str, np.ndarray]] = {}
    if fmt == "ascii":
        words = body.decode("ascii").split()
        pos = 0
        for name, count, props in elements:
            cols: dict[str, list] = {p[0]: [] for p in props}
            for _ in range(count):
                for pname, ptype in props:
                    if isinstance(ptype, tuple):
                        n = int(words[pos]); pos += 1
                        cols[pname].append([float(w) for w in words[pos:pos + n]]); pos += n
                    else:
                        cols[pname].append(float(words[pos])); pos += 1
            kinds = dict(props)
            data[name] = {k: (v if isinstance(kinds[k], tuple) else np.asarray(v))
                          for k, v in cols.items()}
    else:
        bo = "<" if fmt == "binary_little_endian" else ">"
        pos = 0
        for name, count, props in elements:
            has_list = any(isinstance(p[1], tuple) for p in props)
            if not has_list:
                dt = np.dtype([(p, bo + _PLY_TYPES[t]) for p, t in props])
                rec = np.frombuffer(body, dtype=dt, count=count, offset=pos)
                pos += dt.itemsize * count
                data[name] = {p: rec[p] for p, _ in props}
            else:
                data[name], pos = _read_binary_list_element(body, pos, count, props, bo)
    if "vertex" not in data or "face" not in data:
        raise ValueError("needs 'vertex' and 'face' elements")
    v = data["vertex"]
    vertices = np.stack([np.asarray(v[k], np.float64) for k in ("x", "y", "z")], 1)
    flist = data["face"].get("vertex_indices", data["face"].get("vertex_index"))
    if flist is None:
        raise ValueError("face element has no vertex_indices")
    faces = _as_triangles(flist)
    extra = {k: np.asarray(a) for k, a in v.items() if k not in ("x", "y", "z")}
    uvs = None
    tc = data["face"].get("texcoord")
    if tc is not None:
        tc = _as_fixed(tc, 6, "texcoord")
        uvs = tc.reshape(-1, 3, 2)
    return PlyMesh(vertices, faces, extra, uvs)


def _read_binary_list_element(body, pos, count, props, bo):
    # Fast path: every list has the same length (triangles), so the element is a fixed record.
    # Read the first record's list lengths and verify all records agree.
    fields = []
    p = pos
    for pname, ptype in props:
        if isinstance(ptype, tuple):
            _, ctype, itype = ptype
            cdt = np.dtype(bo + _PLY_TYPES[ctype])
            n = int(np.frombuffer(body, cdt, 1, p)[0])
            idt = np.dtype(bo + _PLY_TYPES[itype])
            fields.append((pname + "__n", cdt))
            fields.append((pname, idt, (n,)))
            p += cdt.itemsize + n * idt.itemsize
        else:
            dt = np.dtype(bo + _PLY_TYPES[ptype])
            fields.append((pname, dt))
            p += dt.itemsize
    dt = np.dtype(fields)
    if pos + dt.itemsize * count <= len(body):
        rec = np.frombuffer(body, dtype=dt, count=count, offset=pos)
        ok = all(np.all(rec[f[0]] == rec[f[0]][0]) for f in fields if f[0].endswith("__n"))
        if ok:
            return {f[0]: rec[f[0]] for f in fields if not f[0].endswith("__n")}, pos + dt.itemsize * count
    # Slow path: variable-length lists (e.g. quads mixed with triangles).
    out: dict[str, list] = {pname: [] for pname, _ in props}
    for _ in range(count):
        for pname, ptype in props:
            if isinstance(ptype, tuple):
                _, ctype, itype = ptype
                cdt = np.dtype(bo + _PLY_TYPES[ctype]); idt = np.dtype(bo + _PLY_TYPES[itype])
                n = int(np.frombuffer(body, cdt, 1, pos)[0]); pos += cdt.itemsize
                out[pname].append(np.frombuffer(body, idt, n, pos).tolist()); pos += n * idt.itemsize
            else:
                dt1 = np.dtype(bo + _PLY_TYPES[ptype])
                out[pname].append(np.frombuffer(body, dt1, 1, pos)[0]); pos += dt1.itemsize
    return out, pos


def _as_fixed(lst, n, what):
    arr = np.asarray(lst) if not isinstance(lst, list) else None
    if arr is not None and arr.ndim == 2 and arr.shape[1] == n:
        return arr.astype(np.float64)
    if any(len(x) != n for x in lst):
        raise ValueError(f"{what} lists must have {n} entries")
    return np.asarray(lst, dtype=np.float64)


def _as_triangles(flist) -> np.ndarray:
    arr = np.asarray(flist) if not isinstance(flist, list) else None
    if arr is not None and arr.ndim == 2:
        if arr.shape[1] == 3:
            return arr.astype(np.int64)
        if arr.shape[1] == 4:  # quads: split along the 0-2 diagonal
            return np.concatenate([arr[:, [0, 1, 2]], arr[:, [0, 2, 3]]]).astype(np.int64)
    tris = []
    for f in flist:
        f = [int(i) for i in f]
        if len(f) < 3:
            raise ValueError("a face has fewer than 3 vertices")
        tris += [[f[0], f[i], f[i + 1]] for i in range(1, len(f) - 1)]  # fan triangulation
    return np.asarray(tris, dtype=np.int64).reshape(-1, 3)
