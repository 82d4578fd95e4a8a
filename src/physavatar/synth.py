"""Synthetic captures with known ground truth: the built-in demo data.

A capture is rendered with Mitsuba from a posed Anny body wearing a procedural garment, under
lighting that casts soft self-shadows, with a procedural texture that has detail to track. Its
``ground_truth/`` holds what the pipeline should recover: per-frame meshes, the texture, the
lighting, the garment material when the garment is simulated, and a held-out motion (meshes and
views) for evaluation.

The garment is simulated with a known material (``SynthConfig.material``: one of the simulator's
presets) and the body as collider, starting at rest; with no material it follows the body by
skinning instead. ``capture.json`` says which (``garment_source``).

Building is resumable: images are written one by one, atomically, into ``OUT.partial/`` together
with the config; a rerun with the same config skips what exists, and the folder is renamed to
``OUT`` when complete.
"""

from __future__ import annotations

import hashlib
import json
import shutil
import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import numpy as np

from .body import BodyModel, BodyShape, builtin_motion, linear_blend_skinning
from .camera import Camera, ring_rig
from .capture import BodyPoses, Template, frame_name, save_cameras, save_capture_meta, save_png
from .errors import PhysavatarError
from .files import read_json, save_npz_atomic, write_json_atomic


@dataclass(frozen=True)
class SynthConfig:
    """Everything that defines a synthetic capture (saved as ground_truth/synth_config.json)."""

    preset: str = "custom"
    garment: str = "dress"
    edge_length: float = 0.02  # garment target edge length [m]
    body_topology: str = "collider"  # rendered body = template body = simulation collider
    shape: dict = field(default_factory=lambda: BodyShape().to_dict())
    motion: str = "walk"
    heldout_motion: str = "dance"
    fps: float = 25.0
    frames: int = 48
    heldout_frames: int = 48
    n_ring: int = 8
    n_elevated: int = 2
    width: int = 512
    height: int = 512
    fov_y_deg: float = 40.0
    ring_radius: float = 3.0
    camera_height: float = 1.0
    heldout_cameras: int = 2  # views of the held-out motion rendered for evaluation
    spp: int = 16
    texture_size: int = 1024
    ambient: float = 0.3
    key_radiance: float = 3.0
    material: str = "cotton"  # sim preset: silk (light), cotton (medium), denim (stiff); "" = skinned
    seed: int = 0

    def digest(self) -> str:
        return hashlib.sha1(json.dumps(asdict(self), sort_keys=True).encode()).hexdigest()[:12]


PRESETS: dict[str, SynthConfig] = {
    # For tests: seconds to build.
    "tiny": SynthConfig(preset="tiny", garment="skirt", edge_length=0.05, frames=8,
                        heldout_frames=6, n_ring=3, n_elevated=1, width=96, height=96, spp=4,
                        texture_size=256, heldout_cameras=1),
    # The standard case for benchmarks (docs/synthetic.md gives its size).
    # 32 held-out frames: what `physavatar run` animates and evaluates (1.3 s of the dance).
    "demo": SynthConfig(preset="demo", heldout_frames=32),
}



def preset_config(preset: str, *, garment: str | None = None, motion: str | None = None, frames: int | None = None,
                  seed: int | None = None) -> SynthConfig:
    """The preset's config with the given overrides, each checked (one message naming the option)."""
    from .body.motion import BUILTIN
    from .garment import GARMENTS

    def bad(flag, problem):
        raise PhysavatarError(None, f"option {flag}: {problem}")

    if preset not in PRESETS:
        bad("--preset", f"{preset!r} is not one of {', '.join(PRESETS)}")
    changes = {}
    if garment is not None:
        if garment not in GARMENTS:
            bad("--garment", f"{garment!r} is not one of {', '.join(GARMENTS)}")
        changes["garment"] = garment
    if motion is not None:
        if motion not in BUILTIN:
            bad("--motion", f"{motion!r} is not a built-in motion ({', '.join(BUILTIN)})")
        changes["motion"] = motion
    if frames is not None:
        if frames < 2:
            bad("--frames", "needs at least 2 frames")
        changes["frames"] = frames
    if seed is not None:
        changes["seed"] = seed
    return replace(PRESETS[preset], **changes)

# -- textures ------------------------------------------------------------------------------------

def _value_noise(size: int, cells: int, rng: np.random.Generator) -> np.ndarray:
    """Smooth [size, size] noise in [0, 1] (bicubic-interpolated random lattice)."""
    from scipy.ndimage import zoom

    g = rng.random((cells + 3, cells + 3))
    z = zoom(g, (size + 3 * size / cells) / (cells + 3), order=3)
    return np.clip(z[:size, :size], 0, 1)


def garment_pattern(size: int, rng: np.random.Generator) -> np.ndarray:
    """A linear-RGB fabric print with detail at several scales: stripes, a checker, dots, noise.

    Trackers need texture (paper Sec. 3.1); flat colour would leave the garment's tangential
    motion unobservable.
    """
    u, v = np.meshgrid((np.arange(size) + 0.5) / size, (np.arange(size) + 0.5) / size)
    base = np.array([0.55, 0.12, 0.15])
    alt = np.array([0.85, 0.75, 0.45])
    checker = ((np.floor(u * 16) + np.floor(v * 16)) % 2)[..., None]
    img = base * (1 - checker) + (0.6 * base + 0.4 * alt) * checker
    stripes = (np.sin(2 * np.pi * (u + 0.5 * v) * 40) > 0.6)[..., None]
    img = img * (1 - 0.5 * stripes) + alt * 0.5 * stripes
    # dots of random colours
    n = int(60 * (size / 512) ** 2) + 20
    cu, cv = rng.random(n), rng.random(n)
    rad = rng.uniform(0.006, 0.02, n)
    col = rng.uniform(0.1, 0.95, (n, 3))
    for i in range(n):
        d2 = (u - cu[i]) ** 2 + (v - cv[i]) ** 2
        m = (d2 < rad[i] ** 2)[..., None]
        img = np.where(m, col[i], img)
    img = img * (0.8 + 0.4 * _value_noise(size, 24, rng))[..., None]
    return np.clip(img, 0.02, 0.95).astype(np.float32)


def skin_pattern(size: int, rng: np.random.Generator) -> np.ndarray:
    """Skin-toned reflectance with low-contrast mottling (enough detail to track the body)."""
    skin = np.array([0.62, 0.42, 0.32])
    n1 = _value_noise(size, 32, rng)
    n2 = _value_noise(size, 96, rng)
    img = skin[None, None] * (0.75 + 0.3 * n1[..., None] + 0.15 * n2[..., None])
    return np.clip(img, 0.02, 0.95).astype(np.float32)


def atlas_texture(template: Template, size: int, seed: int) -> np.ndarray:
    """[size, size, 3] linear texture over the template's UV atlas: skin where the body's UVs
    are, the fabric print where the garments' are (row 0 = v 1, the OBJ convention)."""
    rng = np.random.default_rng(seed)
    garment = garment_pattern(size, rng)
    skin = skin_pattern(size, rng)
    # Which atlas texels belong to the garment: rasterize the garment's UV triangles.
    from PIL import Image, ImageDraw

    mask = Image.new("L", (size, size), 0)
    draw = ImageDraw.Draw(mask)
    gfaces = template.garment_mask[template.faces].all(1)
    for tri in template.face_uvs[gfaces]:
        pts = [(float(x * size), float((1 - y) * size)) for x, y in tri]
        draw.polygon(pts, fill=255)
    m = (np.asarray(mask, dtype=np.float32) / 255.0)[..., None]
    # dilate the garment region a little so bilinear lookups at seams stay in-garment
    from scipy.ndimage import maximum_filter

    m = maximum_filter(m, size=(3, 3, 1))
    return (garment * m + skin * (1 - m)).astype(np.float32)


# -- building ------------------------------------------------------------------------------------

def make_cameras(cfg: SynthConfig, target_z: float) -> list[Camera]:
    return ring_rig(cfg.n_ring, cfg.ring_radius, cfg.camera_height, (0.0, 0.0, target_z), cfg.width, cfg.height,
                    cfg.fov_y_deg, n_elevated=cfg.n_elevated, elevated_height=cfg.camera_height + 1.6)


@dataclass
class _Scene:
    cfg: SynthConfig
    body: BodyModel
    template: Template
    garment_weights: np.ndarray  # [Ng, B]
    texture: np.ndarray
    lights: list
    cameras: list[Camera]


def build_template(cfg: SynthConfig) -> tuple[BodyModel, Template, np.ndarray]:
    """Body, body+garment template and the garment's skinning weights for ``cfg``."""
    from .garment import combine_template, garment_skinning_weights, make_garment

    body = BodyModel(BodyShape(**cfg.shape), topology=cfg.body_topology)
    garment = make_garment(cfg.garment, body, edge_length=cfg.edge_length, seed=cfg.seed)
    template = combine_template(body, body.rest_vertices, body.faces, [garment])
    weights = garment_skinning_weights(garment.vertices, body)
    return body, template, weights


def pose_sequences(scene: _Scene, motions: list, progress=True, on_frame=None) -> list[np.ndarray]:
    """[T, V, 3] template vertices along each motion: the body posed, the garment simulated with
    the config's material (or skinned when it names none). The simulations run side by side
    (:mod:`physavatar.parallel`); ``on_frame(motion_index, frame, vertices [V, 3])`` is called in
    this process for every frame as soon as it is simulated (frame 0 first), so the caller can
    render finished frames on the core a finished simulation has freed."""
    t = scene.template
    body_idx = np.flatnonzero(~t.garment_mask)
    gar_idx = np.flatnonzero(t.garment_mask)
    posed = [m.pose(scene.body) for m in motions]
    out = []
    for p in posed:
        V = np.empty((p.vertices.shape[0], len(t.vertices), 3))
        V[:, body_idx] = p.vertices
        out.append(V)
    if scene.cfg.material:
        from .garment_sim import simulate_on_body_job, split_template
        from .parallel import Job, run_jobs
        from .sim import preset

        _, body_faces, part = split_template(t.vertices, t.faces, t.labels, t.boundary, t.rest)
        assert np.array_equal(part.vertex_ids, gar_idx)
        mat = preset(scene.cfg.material)
        for i, V in enumerate(out):  # the garment starts at rest
            V[0, gar_idx] = part.vertices
            if on_frame is not None:
                on_frame(i, 0, V[0])

        def frame_done(i, item):
            f, x = item
            out[i][f, gar_idx] = x
            if on_frame is not None:
                on_frame(i, f, out[i][f])

        jobs = [Job(m.name, simulate_on_body_job, (part, p.vertices, body_faces, mat, scene.cfg.fps),
                    {"send_frames": True}, total=len(p.vertices) - 1) for m, p in zip(motions, posed)]
        for V, Xg in zip(out, run_jobs(jobs, progress=progress, title="synth: simulating", on_item=frame_done)):
            V[:, gar_idx] = Xg
    else:
        for i, (V, p) in enumerate(zip(out, posed)):
            V[:, gar_idx] = linear_blend_skinning(t.vertices[gar_idx], scene.garment_weights, p.bone_transforms)
            if on_frame is not None:
                for f in range(len(V)):
                    on_frame(i, f, V[f])
    return out


def _render_frame(scene: _Scene, vertices: np.ndarray, cameras: list[Camera], seed: int):
    from .render import SceneSpec, load_scene, render
    from .render.avatar import AvatarMeshes

    t = scene.template
    meshes = AvatarMeshes.build(vertices, t.faces, t.face_uvs, t.labels)
    s = load_scene(SceneSpec(meshes=meshes.specs(vertices, scene.texture), lights=scene.lights))
    return [render(s, cam, spp=scene.cfg.spp, seed=seed + i) for i, cam in enumerate(cameras)]


def synthesize(out: str | Path, cfg: SynthConfig, progress=True) -> Path:
    """Write a complete capture folder for ``cfg`` into ``out`` (resumable; see module doc).
    ``progress``: see :mod:`physavatar.progress`."""
    from .progress import resolve
    from .render import save_lights, soft_studio

    out = Path(out)
    if out.exists() and any(out.iterdir()):
        raise PhysavatarError(out, "output folder exists and is not empty (choose another or remove it)")
    work = out.with_name(out.name + ".partial")
    if work.exists():
        try:
            old = read_json(work / "ground_truth" / "synth_config.json")
        except PhysavatarError:
            old = None
        if old != asdict(cfg):
            shutil.rmtree(work)
    work.mkdir(parents=True, exist_ok=True)
    write_json_atomic(work / "ground_truth" / "synth_config.json", asdict(cfg))
    t0 = time.time()

    body, template, weights = build_template(cfg)
    texture = atlas_texture(template, cfg.texture_size, cfg.seed)
    center_z = 0.5 * (body.rest_vertices[:, 2].max() + body.rest_vertices[:, 2].min())
    lights = soft_studio(target=(0.0, 0.0, center_z + 0.2), ambient=cfg.ambient, key_radiance=cfg.key_radiance)
    cameras = make_cameras(cfg, center_z)
    scene = _Scene(cfg, body, template, weights, texture, lights, cameras)

    duration = (cfg.frames - 1) / cfg.fps
    motion = builtin_motion(cfg.motion, body.bone_names, cfg.fps, duration)
    held = builtin_motion(cfg.heldout_motion, body.bone_names, cfg.fps, (cfg.heldout_frames - 1) / cfg.fps)
    source = "simulated" if cfg.material else "skinned"
    meshes_file = work / "ground_truth" / "meshes.npz"
    held_file = work / "ground_truth" / "heldout" / "meshes.npz"
    gt = work / "ground_truth"
    held_dir = gt / "heldout"
    held_cams = cameras[: cfg.n_ring: max(1, cfg.n_ring // max(cfg.heldout_cameras, 1))][: cfg.heldout_cameras]
    views = {"": (work, cameras), "heldout": (held_dir, held_cams)}
    n_frames = {"": cfg.frames, "heldout": cfg.heldout_frames}

    def done(prefix, f):
        base, cams = views[prefix]
        return all((base / "images" / c.name / f"{frame_name(f)}.png").exists()
                   and (base / "masks" / c.name / f"{frame_name(f)}.png").exists() for c in cams)

    prog = resolve(progress)
    total = cfg.frames + cfg.heldout_frames
    with prog.task(f"synth: rendering {len(cameras)} views x {cfg.frames} frames + held-out", total=total) as task:
        task.advance(sum(done(p, f) for p in views for f in range(n_frames[p])))

        def render_frame(prefix, f, v):
            if done(prefix, f):
                return
            base, cams = views[prefix]
            results = _render_frame(scene, v, cams, seed=cfg.seed * 100003 + f * 101 + (7 if prefix else 0))
            for c, r in zip(cams, results):
                save_png(base / "masks" / c.name / f"{frame_name(f)}.png", r.alpha8())
                save_png(base / "images" / c.name / f"{frame_name(f)}.png", r.srgb8())
            task.advance()

        if meshes_file.exists() and held_file.exists():  # resuming: the simulation is done
            verts = np.load(meshes_file)["vertices"].astype(np.float64)
            held_verts = np.load(held_file)["vertices"].astype(np.float64)
        else:
            # Frames are rendered here as the simulations (one process each) produce them, so
            # no core idles once the shorter held-out simulation is done; a frame whose images
            # exist is skipped, so an interrupted build resumes.
            verts, held_verts = pose_sequences(scene, [motion, held], prog,
                                               on_frame=lambda i, f, v: render_frame(("", "heldout")[i], f, v))
            # kept at once: a build interrupted while rendering resumes without simulating again
            save_npz_atomic(meshes_file, vertices=verts.astype(np.float32), faces=template.faces,
                            labels=template.labels.astype(np.uint8), fps=cfg.fps)
            save_npz_atomic(held_file, vertices=held_verts.astype(np.float32), faces=template.faces,
                            labels=template.labels.astype(np.uint8), fps=cfg.fps)
        for f in range(cfg.frames):
            render_frame("", f, verts[f])
        for f in range(cfg.heldout_frames):
            render_frame("heldout", f, held_verts[f])

    # Capture files (small, rewritten every time: cheap and always consistent with cfg).
    frames = list(range(cfg.frames))
    save_capture_meta(work, fps=cfg.fps, frames=frames,
                      extra={"garment_source": source, "synthetic": True, "preset": cfg.preset})
    save_cameras(work, cameras)
    BodyPoses(body.shape, body.bone_names, motion.rotations, motion.root_translation, cfg.body_topology).save(work / "body.npz")
    template.save(work / "template" / "mesh.ply")
    save_png(gt / "texture.png", _srgb8(texture))
    np.save(gt / "texture_linear.npy", texture)
    save_lights(gt / "lighting.json", lights, {"note": "Mitsuba emitters; radiance in linear RGB"})
    if cfg.material:
        from .sim import preset

        preset(cfg.material).save(gt / "material.json")
    save_npz_atomic(gt / "meshes.npz", vertices=verts.astype(np.float32), faces=template.faces,
                    labels=template.labels.astype(np.uint8), fps=cfg.fps)
    held.save(held_dir / "motion.npz")
    save_npz_atomic(held_dir / "meshes.npz", vertices=held_verts.astype(np.float32), faces=template.faces,
                    labels=template.labels.astype(np.uint8), fps=cfg.fps)
    save_cameras(held_dir, held_cams)
    save_npz_atomic(gt / "garment_skinning.npz", weights=weights.astype(np.float32))
    write_json_atomic(gt / "build.json", {"seconds": round(time.time() - t0, 1), "config_digest": cfg.digest(),
                                          "template_vertices": int(len(template.vertices)),
                                          "garment_vertices": int(template.garment_mask.sum()),
                                          "garment_source": source})
    if out.exists():
        out.rmdir()
    work.rename(out)
    return out


def _srgb8(linear: np.ndarray) -> np.ndarray:
    from .render import linear_to_srgb8

    return linear_to_srgb8(linear)


def contact_sheet_for(capture_root: str | Path, frame: int | None = None) -> np.ndarray:
    """All cameras of one frame of a capture in one labelled image [H', W', 3] uint8."""
    from .capture import load_capture
    from .render import contact_sheet

    cap = load_capture(capture_root)
    f = cap.frames[0] if frame is None else frame
    if f not in cap.frames:
        raise PhysavatarError(capture_root, f"frame {f} is not in the capture (frames {cap.frames[0]}..{cap.frames[-1]})")
    imgs = [(cap.image(c.name, f) * 255 + 0.5).astype(np.uint8) for c in cap.cameras]
    return contact_sheet(imgs, [c.name for c in cap.cameras])
