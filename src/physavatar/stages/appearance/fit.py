"""The fit (Eq. 8, A.4): Adam on the texture (and the light intensities) against random training
views, resumable from ``checkpoint.npz``; then the outputs and preview renders.

Each step renders one random (frame, camera) (or ``batch`` of them) with the ``prb`` path tracer;
the loss is the mean squared error in linear RGB inside the eroded foreground mask; Adam's
learning rate is halved every ``lr_decay_every`` steps; the texture is clipped to [0, 1] and the
lights kept >= 0 after each step.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from ...capture import Capture, save_png
from ...files import content_key, load_npz, save_npz_atomic, write_json_atomic
from ...optim import Adam
from ...progress import resolve
from ...render import contact_sheet, linear_to_srgb8
from ...render.avatar import AvatarMeshes
from ...render.lights import save_lights
from ..base import to_dict
from .config import AppearanceConfig, fit_scale
from .data import AppearanceData, load_appearance_data, load_target
from .initial import initial_texture
from .outputs import plot_loss, read_log, write_log
from .scene import InverseRenderer, exposure_scale, initial_lights, light_values, with_light_values


@dataclass
class AppearanceResult:
    """Fit outputs (also written to ``out``): texture [H, W, 3] linear, the initial texture,
    fitted lights, per-iteration log rows, the atlas face_uvs [F, 3, 2]."""

    out: Path
    texture: np.ndarray
    texture_init: np.ndarray
    lights: list
    log: list
    face_uvs: np.ndarray
    face_pixels: np.ndarray
    seconds_per_iteration: float


def _lr(cfg: AppearanceConfig, it: int, base: float) -> float:
    return base * cfg.lr_decay ** (it // cfg.lr_decay_every)


def _views(cfg: AppearanceConfig, it: int, n_frames: int, n_cams: int) -> list[tuple[int, int]]:
    """The (frame index, camera index) pairs of step ``it`` (A.4.3: random per step); seeded by
    (seed, it) so that the sequence does not depend on where a run was resumed."""
    rng = np.random.default_rng([cfg.seed, it])
    return [(int(rng.integers(n_frames)), int(rng.integers(n_cams))) for _ in range(cfg.batch)]


def _resume_key(cfg: AppearanceConfig) -> dict:
    """The settings a checkpoint must have been made with to be resumed (all but those that only
    say how long to run, how often to save and how the previews are rendered)."""
    d = cfg.to_dict()
    d.pop("iterations")
    d.pop("checkpoint_every")
    d.pop("final_spp")
    return d


def _data_key(data: AppearanceData, tex0: np.ndarray, *lights) -> str:
    """What a checkpoint must have been fitted to, besides the settings: the data
    (:attr:`AppearanceData.key`: meshes, frames, cameras, images ...), the initial texture (its
    atlas and projection) and the initial light values. A checkpoint of another tracking run, of
    another capture, or of this one before an image or camera changed, is not resumed but fitted
    again."""
    return content_key(data.key, np.asarray(tex0, np.float64), *[np.asarray(x, np.float64) for x in lights if x is not None])


def fit_appearance(capture: str | Path | Capture, out: str | Path, config: AppearanceConfig = AppearanceConfig(), *,
                   tracked: str | Path | None = None, meshes: str | None = None, lighting: str | Path | None = None,
                   progress=None, data: AppearanceData | None = None) -> AppearanceResult:
    """Fit the texture and lights (module doc) and write everything into ``out``.

    Args:
        capture: capture folder (or loaded capture). tracked: tracking output folder (``tracked.npz``).
        meshes: ``"tracked"`` or ``"gt"`` instead of ``config.meshes``.
        lighting: lights file for ``light="studio"`` (default ``ground_truth/lighting.json``).
        progress: anything :func:`physavatar.progress.resolve` accepts.
        data: preloaded :class:`AppearanceData` (tests, benchmarks) instead of capture, tracked
            and meshes (its source is recorded as ``meshes``).
    """
    cfg = config if meshes is None else replace(config, meshes=meshes)
    if data is None:
        data = load_appearance_data(capture, tracked, cfg.meshes, cfg.texture_size, cfg.cameras)
    elif data.source != cfg.meshes:
        cfg = replace(cfg, meshes=data.source)
    # small captures are fitted at (up to) full resolution (config.min_size)
    cfg = replace(cfg, scale=min(fit_scale(cfg, c.width, c.height) for c in data.cameras))
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    prog = resolve(progress)
    t = data.template
    frames_idx = list(range(0, len(data.frames), cfg.frame_stride))
    write_json_atomic(out / "config.json", {**to_dict(cfg), "tracked": None if tracked is None else str(tracked),
                                            "capture": str(data.capture.root)})

    meshes_ = AvatarMeshes.build(t.vertices, t.faces, t.face_uvs, t.labels)
    lights0 = initial_lights(cfg, data.capture, lighting)
    white = np.ones((cfg.texture_size, cfg.texture_size, 3), np.float32)
    renderer = InverseRenderer(meshes_, data.vertices[0], white, lights0, cfg.max_depth)
    amb0, key0 = light_values(lights0)
    if renderer.key_key is None:
        key0 = None
    light_key = None
    if cfg.light == "env":  # the environment map, fitted in closed form with the albedo (.envlight)
        from ...render import EnvMap
        from .envlight import fitted_env_light
        from .project import TexelPoints

        env, _ = fitted_env_light(data, cfg, out, renderer, TexelPoints.of(t.face_uvs, cfg.texture_size), prog)
        lights0 = [EnvMap(env, name=lights0[0].name)]
        light_key = np.round(env.mean((0, 1)), 6).tolist() + [float(np.round(env.std(), 6))]

    # 1-2. atlas and initial texture T_0 (projected, or per-face colours averaged over frames)
    face_uvs, face_pixels, tex0 = initial_texture(data, cfg, out, prog, renderer=renderer, ambient=amb0, key=key0,
                                                  light_key=light_key)

    # 3. inverse rendering, resumable
    ckpt = out / "checkpoint.npz"
    state = {"texture": tex0.astype(np.float64)}
    if amb0 is not None:
        state["ambient"] = amb0
    if key0 is not None:
        state["key"] = key0
    fitted_keys = ["texture"] + ([k for k in ("ambient", "key") if k in state] if cfg.fit_light else [])
    adam = Adam({k: state[k].shape for k in fitted_keys})
    log: list[dict] = []
    start = 0
    exposure = None
    data_key = _data_key(data, tex0, amb0, key0)
    if ckpt.is_file():
        z = load_npz(ckpt)
        if json.loads(str(z["resume_key"])) == _resume_key(cfg) and \
                (str(z["data_key"]) if "data_key" in z else None) == data_key:
            for k in state:
                state[k] = z[k]
            adam.load_state_dict(z)
            start = int(z["iteration"])
            log = read_log(out / "fit_log.csv")[:start]
            exposure = float(z["exposure"])
    if exposure is None:
        if cfg.light == "studio" and cfg.init == "faces":
            # Known lights: T_0 holds shaded radiance, so bring it to the right overall level
            # (one global factor) before Adam's small steps have to climb there.
            exposure = exposure_scale(renderer, data, tex0, state.get("ambient"), state.get("key"), cfg)
            state["texture"] = np.clip(tex0 * exposure, 0.0, 1.0)
        else:
            exposure = 1.0  # the paper: T_0 as is, L_a = 1; a projected T_0 is already albedo under the lights
    lr_of = {"texture": cfg.lr, "ambient": cfg.light_lr or cfg.lr, "key": cfg.light_lr or cfg.lr}

    with prog.task(f"appearance: inverse rendering ({cfg.light})", total=cfg.iterations) as task:
        if start:
            task.advance(min(start, cfg.iterations))
        for it in range(start, cfg.iterations):
            t0 = time.time()
            grads = {k: np.zeros_like(state[k]) for k in fitted_keys}
            loss = 0.0
            for j, (ti, ci) in enumerate(_views(cfg, it, len(frames_idx), len(data.cameras))):
                fi = frames_idx[ti]
                cam = data.cameras[ci]
                target, mask = load_target(data.capture, cam, data.frames[fi], cfg.scale, cfg.erode_px)
                renderer.set_vertices(data.vertices[fi], tag=fi)
                l, gT, gA, gK = renderer.loss_and_grads(cam.scaled(cfg.scale), target, mask, state["texture"],
                                                        state.get("ambient"), state.get("key"), spp=cfg.spp,
                                                        seed=it * cfg.batch + j)
                loss += l / cfg.batch
                grads["texture"] += gT / cfg.batch
                if "ambient" in grads and gA is not None:
                    grads["ambient"] += gA / cfg.batch
                if "key" in grads and gK is not None:
                    grads["key"] += gK / cfg.batch
            adam.step(state, grads, {k: _lr(cfg, it, lr_of[k]) for k in fitted_keys})
            state["texture"] = np.clip(state["texture"], 0.0, 1.0)  # A.4.3: legal colours
            for k in ("ambient", "key"):
                if k in state:
                    state[k] = np.maximum(state[k], 0.0)
            amb = state.get("ambient", np.full(3, np.nan))
            log.append({"iteration": it, "loss": loss, "lr": _lr(cfg, it, cfg.lr), "ambient_r": amb[0],
                        "ambient_g": amb[1], "ambient_b": amb[2],
                        "key": float(np.mean(state["key"])) if "key" in state else float("nan"),
                        "seconds": time.time() - t0})
            task.advance(loss=loss)
            if (it + 1) % cfg.checkpoint_every == 0 or it + 1 == cfg.iterations:
                save_npz_atomic(ckpt, iteration=np.int64(it + 1), resume_key=np.array(json.dumps(_resume_key(cfg))),
                                data_key=np.array(data_key),
                                exposure=np.float64(exposure), **state, **adam.state_dict())
                write_log(out / "fit_log.csv", log)
    # per-iteration time from the log, so that a resumed run reports the same figure
    sec_it = float(np.mean([r["seconds"] for r in log])) if log else float("nan")

    texture = state["texture"].astype(np.float32)
    lights = with_light_values(lights0, state.get("ambient"), state.get("key"))
    np.save(out / ".texture_linear.tmp.npy", texture)
    (out / ".texture_linear.tmp.npy").replace(out / "texture_linear.npy")
    save_png(out / "texture.png", linear_to_srgb8(texture))
    save_lights(out / "light.json", lights, {"model": cfg.light, "exposure_init": exposure,
                                             "note": "fitted lights; radiance in linear RGB"})
    write_log(out / "fit_log.csv", log)
    plot_loss(log, out / "loss.png")

    # final renders at final_spp: target | fit, a few training views of the first frame
    tiles, labels = [], []
    renderer.set_vertices(data.vertices[0], tag=0)
    with prog.task("appearance: preview", total=min(4, len(data.cameras))) as task:
        for cam in data.cameras[:4]:
            target, _ = load_target(data.capture, cam, data.frames[0], 1.0, 0)
            r = renderer.render(cam, texture, state.get("ambient"), state.get("key"), spp=cfg.final_spp, seed=1)
            tiles += [linear_to_srgb8(target), r.srgb8()]
            labels += [f"{cam.name} image", f"{cam.name} fit"]
            task.advance()
    save_png(out / "preview.png", contact_sheet(tiles, labels))
    return AppearanceResult(out, texture, tex0, lights, log, face_uvs, face_pixels, sec_it)
