"""Export an animated mesh sequence to USD, glTF binary, and OBJ / PLY sequences.

One input, ``MeshSequence`` (vertices [T, V, 3] in metres, z up; faces [F, 3]; optional
per-face-corner UVs [F, 3, 2] with the origin at the image's bottom-left, as in OBJ and USD;
optional texture PNG; fps), and one writer per format:

- ``export_usd``: a UsdGeom.Mesh whose ``points`` carry one time sample per frame (time code =
  frame index, ``timeCodesPerSecond`` = fps), faceVarying ``primvars:st``, a UsdPreviewSurface
  material reading the texture copied next to the file. Blender imports it as an animated mesh
  cache. Binary crate (.usdc) by default, text (.usda) on request.
- ``export_glb``: frame 0 is the base mesh, every later frame a morph target (POSITION
  displacement), and one animation drives the morph weights (one-hot per key frame; LINEAR
  interpolation blends consecutive frames, STEP holds them). This is the standard way to carry
  per-vertex animation in glTF 2.0. Y up as glTF requires, texture embedded.
- ``export_obj_sequence`` / ``export_ply_sequence``: one file per frame (``frame_0000.obj`` ...),
  UVs included, an .mtl naming the texture for OBJ.

Every file is written atomically (temporary name in the same folder, then ``os.replace``).
Bad input raises ``ExportError`` naming the output path. docs/export.md has the details.
"""

from __future__ import annotations

import io
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .errors import PhysavatarError
from .files import PlyMesh, atomic_path, write_bytes_atomic, write_ply, write_text_atomic
from .geometry import split_uv_seams, vertex_normals

_PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


class ExportError(PhysavatarError, ValueError):
    """An export that cannot be written: ``path`` is the output, ``problem`` what is wrong."""


@dataclass(frozen=True)
class MeshSequence:
    """An animated triangle mesh with fixed topology.

    Attributes:
        vertices: [T, V, 3] positions in metres (world frame, z up), one row per frame.
        faces: [F, 3] vertex indices, counter-clockwise seen from outside.
        uvs: [F, 3, 2] texture coordinates per face corner (origin bottom-left), or None.
        texture: path of a PNG file, PNG bytes, or an [H, W, 3|4] image array (uint8, or float
            in [0, 1]), or None. Requires ``uvs``.
        fps: frames per second of the sequence.
    """

    vertices: np.ndarray
    faces: np.ndarray
    uvs: np.ndarray | None = None
    texture: str | Path | np.ndarray | bytes | None = None
    fps: float = 30.0

    @property
    def n_frames(self) -> int:
        return int(np.shape(self.vertices)[0])

    def validated(self, path: str | Path) -> "MeshSequence":
        """Checked copy with float64 vertices / UVs and int64 faces; ExportError naming ``path``."""
        def bad(problem: str) -> ExportError:
            return ExportError(path, problem)

        v = np.asarray(self.vertices)
        if v.ndim != 3 or v.shape[2] != 3 or v.shape[0] < 1 or v.shape[1] < 3:
            raise bad(f"vertices must be [T, V, 3] with T >= 1, V >= 3; got shape {v.shape}")
        if not np.issubdtype(v.dtype, np.number):
            raise bad(f"vertices must be numeric, got dtype {v.dtype}")
        v = v.astype(np.float64)
        if not np.all(np.isfinite(v)):
            t = int(np.argwhere(~np.isfinite(v))[0, 0])
            raise bad(f"vertices contain NaN or inf (first in frame {t})")
        f = np.asarray(self.faces)
        if f.ndim != 2 or f.shape[1] != 3 or f.shape[0] < 1:
            raise bad(f"faces must be [F, 3] with F >= 1; got shape {f.shape}")
        if not np.issubdtype(f.dtype, np.integer):
            raise bad(f"faces must be integers, got dtype {f.dtype}")
        f = f.astype(np.int64)
        if f.min() < 0 or f.max() >= v.shape[1]:
            raise bad(f"face indices must lie in [0, {v.shape[1] - 1}], found "
                      f"[{f.min()}, {f.max()}]")
        uv = None
        if self.uvs is not None:
            uv = np.asarray(self.uvs)
            if uv.shape != (f.shape[0], 3, 2):
                raise bad(f"uvs must be [F, 3, 2] = {(f.shape[0], 3, 2)}, got {uv.shape}")
            uv = uv.astype(np.float64)
            if not np.all(np.isfinite(uv)):
                raise bad("uvs contain NaN or inf")
        if self.texture is not None and uv is None:
            raise bad("a texture needs uvs")
        fps = float(self.fps)
        if not np.isfinite(fps) or fps <= 0:
            raise bad(f"fps must be a positive number, got {self.fps}")
        tex = None if self.texture is None else _texture_png(self.texture, path)
        return MeshSequence(v, f, uv, tex, fps)


def _texture_png(texture, path) -> bytes:
    """PNG bytes of a texture given as a file, PNG bytes or an image array."""
    if isinstance(texture, bytes):
        if not texture.startswith(_PNG_MAGIC):
            raise ExportError(path, "texture bytes are not a PNG image")
        return texture
    if isinstance(texture, (str, Path)):
        src = Path(texture)
        if not src.is_file():
            raise ExportError(path, f"texture {src} not found")
        data = src.read_bytes()
        if not data.startswith(_PNG_MAGIC):
            raise ExportError(path, f"texture {src} is not a PNG file")
        return data
    from PIL import Image

    img = np.asarray(texture)
    if img.ndim != 3 or img.shape[2] not in (3, 4):
        raise ExportError(path, f"texture array must be [H, W, 3|4], got {img.shape}")
    if img.dtype != np.uint8:
        img = np.asarray(img, dtype=np.float64)
        if not np.all(np.isfinite(img)):
            raise ExportError(path, "texture contains NaN or inf")
        img = np.round(np.clip(img, 0.0, 1.0) * 255).astype(np.uint8)
    buf = io.BytesIO()
    Image.fromarray(img).save(buf, format="PNG")
    return buf.getvalue()


# -- USD -----------------------------------------------------------------------------------------
def export_usd(path: str | Path, seq: MeshSequence, *, ascii: bool = False,
               normals: bool = False, prim_name: str = "avatar") -> Path:
    """Write ``seq`` as USD with time-sampled points; returns the path written.

    path: ``.usdc`` (binary crate), ``.usda`` (text) or ``.usd`` (crate, or text with
    ``ascii=True``). The texture, if any, is copied next to it as ``<stem>_texture.png`` and
    referenced by that relative path. ``normals=True`` adds time-sampled area-weighted vertex
    normals (otherwise importers compute their own). Layout: /<prim_name> (Xform, default prim)
    with /<prim_name>/mesh (Mesh) and /<prim_name>/Looks/material.
    """
    from pxr import Sdf, Usd, UsdGeom, Vt

    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in (".usd", ".usda", ".usdc"):
        raise ExportError(path, "USD output must end in .usd, .usda or .usdc")
    if ascii and suffix == ".usdc":
        raise ExportError(path, "ascii=True conflicts with the .usdc extension; use .usda or .usd")
    seq = seq.validated(path)
    v, f, uv = seq.vertices, seq.faces, seq.uvs

    stage = Usd.Stage.CreateInMemory()
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.z)  # DESIGN.md: metres, z up
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    stage.SetStartTimeCode(0)
    stage.SetEndTimeCode(seq.n_frames - 1)
    stage.SetTimeCodesPerSecond(seq.fps)
    stage.SetFramesPerSecond(seq.fps)

    root = UsdGeom.Xform.Define(stage, f"/{prim_name}")
    stage.SetDefaultPrim(root.GetPrim())
    mesh = UsdGeom.Mesh.Define(stage, f"/{prim_name}/mesh")
    mesh.CreateFaceVertexCountsAttr(Vt.IntArray.FromNumpy(np.full(len(f), 3, np.int32)))
    mesh.CreateFaceVertexIndicesAttr(Vt.IntArray.FromNumpy(f.reshape(-1).astype(np.int32)))
    # USD's default scheme is Catmull-Clark, which viewers would subdivide; ours is a cage-free
    # triangle mesh.
    mesh.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
    mesh.CreateOrientationAttr(UsdGeom.Tokens.rightHanded)
    points = mesh.CreatePointsAttr()
    extent = mesh.CreateExtentAttr()
    normal_attr = None
    if normals:
        normal_attr = mesh.CreateNormalsAttr()
        mesh.SetNormalsInterpolation(UsdGeom.Tokens.vertex)
        nrm = vertex_normals(v, f)
    for t in range(seq.n_frames):
        frame = v[t].astype(np.float32)
        points.Set(Vt.Vec3fArray.FromNumpy(frame), Usd.TimeCode(t))
        extent.Set(Vt.Vec3fArray.FromNumpy(np.stack([frame.min(0), frame.max(0)])),
                   Usd.TimeCode(t))
        if normal_attr is not None:
            normal_attr.Set(Vt.Vec3fArray.FromNumpy(nrm[t].astype(np.float32)), Usd.TimeCode(t))

    if uv is not None:
        # Indexed faceVarying primvar: shared corners (most of them) are stored once.
        uniq, index = np.unique(uv.reshape(-1, 2).astype(np.float32), axis=0, return_inverse=True)
        st = UsdGeom.PrimvarsAPI(mesh).CreatePrimvar(
            "st", Sdf.ValueTypeNames.TexCoord2fArray, UsdGeom.Tokens.faceVarying)
        st.Set(Vt.Vec2fArray.FromNumpy(uniq))
        st.SetIndices(Vt.IntArray.FromNumpy(index.reshape(-1).astype(np.int32)))

    tex_name = None
    if seq.texture is not None:
        tex_name = f"{path.stem}_texture.png"
        write_bytes_atomic(path.parent / tex_name, seq.texture)
    _usd_material(stage, mesh, f"/{prim_name}/Looks/material", tex_name)

    args = {"format": "usda" if ascii else "usdc"} if suffix == ".usd" else {}
    with atomic_path(path) as tmp:
        if not stage.GetRootLayer().Export(str(tmp), "written by physavatar", args):
            raise ExportError(path, "USD layer export failed")
    return path


def _usd_material(stage, mesh, mat_path: str, tex_name: str | None) -> None:
    """UsdPreviewSurface, textured through a UsdUVTexture reading primvar ``st`` when a texture
    is given (the recipe of the USD "Simple Shading" tutorial, which Blender's importer maps to a
    Principled BSDF with an Image Texture node)."""
    from pxr import Sdf, UsdShade

    from pxr import UsdGeom

    UsdGeom.Scope.Define(stage, mat_path.rsplit("/", 1)[0])
    material = UsdShade.Material.Define(stage, mat_path)
    pbr = UsdShade.Shader.Define(stage, f"{mat_path}/PreviewSurface")
    pbr.CreateIdAttr("UsdPreviewSurface")
    pbr.CreateInput("roughness", Sdf.ValueTypeNames.Float).Set(0.9)
    pbr.CreateInput("metallic", Sdf.ValueTypeNames.Float).Set(0.0)
    material.CreateSurfaceOutput().ConnectToSource(pbr.ConnectableAPI(), "surface")
    diffuse = pbr.CreateInput("diffuseColor", Sdf.ValueTypeNames.Color3f)
    if tex_name is None:
        from pxr import Gf

        diffuse.Set(Gf.Vec3f(0.8, 0.8, 0.8))
    else:
        # varname is a string since UsdPreviewSurface 2.5 (usd-core's validator rejects token)
        st_name = material.CreateInput("frame:stPrimvarName", Sdf.ValueTypeNames.String)
        st_name.Set("st")
        reader = UsdShade.Shader.Define(stage, f"{mat_path}/stReader")
        reader.CreateIdAttr("UsdPrimvarReader_float2")
        reader.CreateInput("varname", Sdf.ValueTypeNames.String).ConnectToSource(st_name)
        tex = UsdShade.Shader.Define(stage, f"{mat_path}/diffuseTexture")
        tex.CreateIdAttr("UsdUVTexture")
        tex.CreateInput("file", Sdf.ValueTypeNames.Asset).Set(f"./{tex_name}")
        tex.CreateInput("st", Sdf.ValueTypeNames.Float2).ConnectToSource(
            reader.ConnectableAPI(), "result")
        tex.CreateInput("sourceColorSpace", Sdf.ValueTypeNames.Token).Set("sRGB")
        tex.CreateInput("wrapS", Sdf.ValueTypeNames.Token).Set("repeat")
        tex.CreateInput("wrapT", Sdf.ValueTypeNames.Token).Set("repeat")
        rgb = tex.CreateOutput("rgb", Sdf.ValueTypeNames.Float3)
        diffuse.ConnectToSource(rgb)
    UsdShade.MaterialBindingAPI.Apply(mesh.GetPrim()).Bind(material)


# -- glTF binary ---------------------------------------------------------------------------------
# glTF is y up; our world is z up. (x, y, z) -> (x, z, -y) is the rotation Blender's glTF
# exporter applies (+Y up), so its importer restores the original coordinates.
Z_UP_TO_Y_UP = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])


def export_glb(path: str | Path, seq: MeshSequence, *, interpolation: str = "LINEAR",
               name: str = "avatar") -> Path:
    """Write ``seq`` as a binary glTF with morph-target animation; returns the path written.

    Base mesh = frame 0; morph target k = frame k+1 minus frame 0 (T-1 targets); the animation
    has one key frame per frame at t/fps whose weights are one-hot on that frame's target (all
    zero at frame 0). ``interpolation``: "LINEAR" (blends neighbouring frames, i.e. linear vertex
    interpolation) or "STEP". Vertices are split along UV seams (glTF has per-vertex UVs only);
    coordinates are rotated to glTF's y up (``Z_UP_TO_Y_UP``); V texture coordinates flipped to
    glTF's top-left origin; the texture is embedded as PNG.
    """
    import pygltflib as g

    path = Path(path)
    if path.suffix.lower() != ".glb":
        raise ExportError(path, "glTF binary output must end in .glb")
    if interpolation not in ("LINEAR", "STEP"):
        raise ExportError(path, f"interpolation must be LINEAR or STEP, got {interpolation!r}")
    seq = seq.validated(path)
    v, f, uv = seq.vertices, seq.faces, seq.uvs
    if uv is not None:
        split = split_uv_seams(v[0], f, uv)
        f, vuv = split.faces, split.uvs
        v = v[:, split.vertex_map]
    frames = (v @ Z_UP_TO_Y_UP.T).astype(np.float32)  # [T, V', 3]
    T = seq.n_frames

    blob = bytearray()
    views: list = []
    accessors: list = []

    def add_view(data: bytes, target: int | None = None) -> int:
        while len(blob) % 4:  # accessors need 4-byte aligned offsets for float32 / uint32
            blob.append(0)
        views.append(g.BufferView(buffer=0, byteOffset=len(blob), byteLength=len(data),
                                  target=target))
        blob.extend(data)
        return len(views) - 1

    def add_accessor(arr: np.ndarray, kind: str, comp: int, target: int | None = None,
                     bounds: bool = False) -> int:
        view = add_view(arr.tobytes(), target)
        acc = g.Accessor(bufferView=view, componentType=comp, count=len(arr), type=kind)
        if bounds:  # required for POSITION (and morph POSITION) and animation inputs
            flat = arr.reshape(len(arr), -1)
            acc.min, acc.max = flat.min(0).tolist(), flat.max(0).tolist()
        accessors.append(acc)
        return len(accessors) - 1

    attrs = g.Attributes(POSITION=add_accessor(frames[0], g.VEC3, g.FLOAT, g.ARRAY_BUFFER, True))
    if uv is not None:
        st = np.stack([vuv[:, 0], 1.0 - vuv[:, 1]], axis=1).astype(np.float32)
        attrs.TEXCOORD_0 = add_accessor(st, g.VEC2, g.FLOAT, g.ARRAY_BUFFER)
    indices = add_accessor(f.reshape(-1).astype(np.uint32), g.SCALAR, g.UNSIGNED_INT,
                           g.ELEMENT_ARRAY_BUFFER)
    targets = [{"POSITION": add_accessor(frames[t] - frames[0], g.VEC3, g.FLOAT,
                                         g.ARRAY_BUFFER, True)} for t in range(1, T)]

    material = g.Material(name="material", doubleSided=True,
                          pbrMetallicRoughness=g.PbrMetallicRoughness(
                              baseColorFactor=[1.0, 1.0, 1.0, 1.0] if seq.texture is not None
                              else [0.8, 0.8, 0.8, 1.0],
                              metallicFactor=0.0, roughnessFactor=0.9))
    images, textures, samplers = [], [], []
    if seq.texture is not None:
        images.append(g.Image(bufferView=add_view(seq.texture), mimeType="image/png"))
        samplers.append(g.Sampler(magFilter=g.LINEAR, minFilter=g.LINEAR_MIPMAP_LINEAR,
                                  wrapS=g.REPEAT, wrapT=g.REPEAT))
        textures.append(g.Texture(sampler=0, source=0))
        material.pbrMetallicRoughness.baseColorTexture = g.TextureInfo(index=0)

    prim = g.Primitive(attributes=attrs, indices=indices, material=0, mode=g.TRIANGLES,
                       targets=targets or None)
    mesh = g.Mesh(name=name, primitives=[prim], weights=[0.0] * (T - 1) or None,
                  # Blender's importer names shape keys after extras.targetNames
                  extras={"targetNames": [f"frame_{t:04d}" for t in range(1, T)]})
    animations = []
    if T > 1:
        times = (np.arange(T) / seq.fps).astype(np.float32)
        weights = np.zeros((T, T - 1), np.float32)
        weights[np.arange(1, T), np.arange(T - 1)] = 1.0
        sampler = g.AnimationSampler(input=add_accessor(times, g.SCALAR, g.FLOAT, bounds=True),
                                     output=add_accessor(weights.reshape(-1), g.SCALAR, g.FLOAT),
                                     interpolation=interpolation)
        channel = g.AnimationChannel(sampler=0,
                                     target=g.AnimationChannelTarget(node=0, path="weights"))
        animations.append(g.Animation(name="vertex_animation", samplers=[sampler],
                                      channels=[channel]))

    gltf = g.GLTF2(
        asset=g.Asset(version="2.0", generator="physavatar"),
        scene=0, scenes=[g.Scene(nodes=[0])], nodes=[g.Node(mesh=0, name=name)],
        meshes=[mesh], materials=[material], images=images, textures=textures,
        samplers=samplers, animations=animations, accessors=accessors, bufferViews=views,
        buffers=[g.Buffer(byteLength=len(blob))],
        extras={"fps": seq.fps, "frames": T, "source_up_axis": "z"})
    gltf.set_binary_blob(bytes(blob))
    with atomic_path(path) as tmp:
        if not gltf.save_binary(str(tmp)):
            raise ExportError(path, "glTF binary write failed")
    return path


# -- OBJ / PLY sequences -------------------------------------------------------------------------
def frame_name(t: int, ext: str) -> str:
    """File name of frame ``t`` in an OBJ/PLY sequence: frame_0000.obj, frame_0001.obj, ..."""
    return f"frame_{t:04d}.{ext}"


def export_obj_sequence(folder: str | Path, seq: MeshSequence, *,
                        material_name: str = "material") -> list[Path]:
    """One OBJ per frame in ``folder`` (``frame_0000.obj`` ...); returns the paths written.

    Each OBJ has ``v`` (9 significant digits), and with UVs ``vt`` and ``f v/vt`` faces; with a
    texture, ``material.mtl`` (``map_Kd texture.png``) and ``texture.png`` are written once and
    every frame names them (``mtllib`` / ``usemtl``). Vertex order and count equal the input's.
    """
    folder = Path(folder)
    seq = seq.validated(folder)
    folder.mkdir(parents=True, exist_ok=True)
    head = [f"# physavatar mesh sequence, {seq.n_frames} frames at {seq.fps:g} fps"]
    if seq.texture is not None:
        write_bytes_atomic(folder / "texture.png", seq.texture)
        write_text_atomic(folder / f"{material_name}.mtl",
                          f"newmtl {material_name}\nKa 0 0 0\nKd 1 1 1\nKs 0 0 0\nillum 1\n"
                          f"map_Kd texture.png\n")
        head.append(f"mtllib {material_name}.mtl")
    # Topology and UVs are the same in every frame: format them once.
    tail = io.StringIO()
    if seq.uvs is not None:
        uniq, index = np.unique(seq.uvs.reshape(-1, 2), axis=0, return_inverse=True)
        np.savetxt(tail, uniq, fmt="vt %.9g %.9g")
        if seq.texture is not None:
            tail.write(f"usemtl {material_name}\n")
        corners = np.stack([seq.faces.reshape(-1) + 1, index.reshape(-1) + 1], 1)
        np.savetxt(tail, corners.reshape(-1, 6), fmt="f %d/%d %d/%d %d/%d")
    else:
        np.savetxt(tail, seq.faces + 1, fmt="f %d %d %d")
    tail_text = tail.getvalue()
    written = []
    for t in range(seq.n_frames):
        buf = io.StringIO()
        buf.write("\n".join(head) + f"\n# frame {t}\no {material_name}_mesh\n")
        np.savetxt(buf, seq.vertices[t], fmt="v %.9g %.9g %.9g")
        buf.write(tail_text)
        out = folder / frame_name(t, "obj")
        write_text_atomic(out, buf.getvalue())
        written.append(out)
    return written


def export_ply_sequence(folder: str | Path, seq: MeshSequence) -> list[Path]:
    """One binary PLY per frame in ``folder`` (``frame_0000.ply`` ...); returns the paths written.

    Written with ``physavatar.files.write_ply``: float32 positions, input vertex order, UVs as the
    MeshLab per-corner face property ``texcoord``. The texture, if any, is saved once as
    ``texture.png`` in the folder.
    """
    folder = Path(folder)
    seq = seq.validated(folder)
    folder.mkdir(parents=True, exist_ok=True)
    if seq.texture is not None:
        write_bytes_atomic(folder / "texture.png", seq.texture)
    written = []
    for t in range(seq.n_frames):
        out = folder / frame_name(t, "ply")
        write_ply(out, PlyMesh(seq.vertices[t], seq.faces, face_uvs=seq.uvs))
        written.append(out)
    return written


def export(path: str | Path, seq: MeshSequence, fmt: str | None = None, **options):
    """Write ``seq`` in the format named by ``fmt`` or by the path's extension.

    ``.usd``/``.usda``/``.usdc`` -> export_usd; ``.glb`` -> export_glb; ``fmt="obj"`` or
    ``"ply"`` (``path`` is then a folder) -> the per-frame sequences. ``options`` go to the writer.
    """
    path = Path(path)
    fmt = (fmt or path.suffix.lstrip(".")).lower()
    if fmt in ("usd", "usda", "usdc"):
        return export_usd(path, seq, **options)
    if fmt == "glb":
        return export_glb(path, seq, **options)
    if fmt == "obj":
        return export_obj_sequence(path, seq, **options)
    if fmt == "ply":
        return export_ply_sequence(path, seq, **options)
    raise ExportError(path, f"unknown export format {fmt!r} (usd, usda, usdc, glb, obj, ply)")


__all__ = ["ExportError", "MeshSequence", "export", "export_usd", "export_glb",
           "export_obj_sequence", "export_ply_sequence",
           "frame_name", "Z_UP_TO_Y_UP"]
