"""Physics-based appearance: a relightable diffuse texture by inverse rendering (PhysAvatar Sec. 3.3).

Given the mesh sequence V_1:T (tracked, or the capture's ground truth) and per-face colours c_t
(the tracking stage's Gaussian colours, or colours read from the images here), the paper fits a
time-invariant diffuse texture T and a global ambient light L_a with Mitsuba 3 (Eq. 8):

    L_rgb = min_{T, L_a} sum_{i,t} || I_{i,t} - R(T, L_a, V_t, c_{i,t}) ||²

The stage is :func:`run` (``run(capture, out=, config=AppearanceConfig(...), tracked=)``); its
modules, in the order of the steps:

- :mod:`.config`   :class:`~.config.AppearanceConfig` (the command-line options), the ``--quick``
                   preset, the settings of ``physavatar run``;
- :mod:`.data`     the capture and mesh sequence (:class:`~.data.AppearanceData`), training targets;
- :mod:`.texture`  1. UV atlas: the template's per-corner UVs, or an automatic ``xatlas`` unwrap
                   when it has none (the paper unwraps by hand in Blender); texel-to-face maps
                   and splatting;
- :mod:`.initial`  2. initial texture T_0: projected (default; :mod:`.project`: each texel
                   looked up in the views that see it, with visibility and occlusion-edge tests,
                   shading divided out in closed form, unseen texels inpainted along the
                   surface), or the paper's per-face colours averaged over frames, splatted into
                   the atlas (``init="faces"``);
- :mod:`.project`  the projection: texel surface points, ray-cast visibility, least squares,
                   harmonic inpainting over the face graph;
- :mod:`.scene`    the differentiable scene and the two lighting models:

                   - ``ambient`` (the paper): one ambient radiance L_a ∈ R³, initialised to 1.
                   - ``studio``: ambient plus the capture's known key light (geometry from the
                     lighting file, ``ground_truth/lighting.json`` for synthetic captures), both
                     intensities fitted. Ambient light alone cannot produce directional shading,
                     so under a key light the ``ambient`` fit bakes the key's shading into the
                     texture; ``studio`` can factor it out;
- :mod:`.envlight` the ``env`` light model: a smooth environment map (a constant plus 12 lobes)
                   fitted with the albedo by alternating least squares before the projection;
- :mod:`.fit`      3. inverse rendering (A.4): each step renders one random (frame, camera) (or a
                   small batch) with the ``prb`` path tracer, the loss is the mean squared error in
                   linear RGB inside the foreground mask eroded by 2 px, Adam with lr 0.01 halved
                   every 500 steps, texture clipped to [0, 1] after each step;
- :mod:`.outputs`  the fit's log and plot, :class:`~.outputs.FittedAppearance` (a fit's folder loaded);
- :mod:`.evaluation` texture PSNR, baked shading, held-out renders (benchmarks, tests).

Relighting (rendering the texture under any light of ``physavatar.render``) is the ``relight``
stage, :mod:`physavatar.stages.relight`.

Outputs (``out/``)::

    texture.png, texture_linear.npy    fitted albedo atlas (sRGB PNG; linear float32 [H, W, 3])
    texture_init_linear.npy            T_0 (the "w/o appearance" ablation of Table 2)
    atlas.npz                          face_uvs [F, 3, 2], face_colors [F, 3] (T_0's source),
                                       face_pixels [F] (training pixels that saw each face; with
                                       tracked colours counted on 8 frames spread over the sequence)
    light.json                         fitted lights (same format as lighting.json)
    fit_log.csv, loss.png              per-iteration loss, lr, lights, seconds
    preview.png                        target | fitted render of a few training views (final spp)
    config.json                        the exact AppearanceConfig (+ the tracked and capture paths)
    checkpoint.npz                     state every ``checkpoint_every`` steps (a rerun resumes)

Shapes follow docs/rendering.md: textures are [H, W, 3] linear, row 0 = v 1 (OBJ convention).
"""

from __future__ import annotations

from pathlib import Path

from .config import AppearanceConfig, pipeline_config, quick_preset
from .fit import AppearanceResult, fit_appearance

__all__ = ["AppearanceConfig", "AppearanceResult", "pipeline_config", "quick_preset", "run"]


def run(capture: Path, *, out: Path, config: AppearanceConfig, tracked: Path | None = None,
        lighting: Path | None = None, progress=None) -> AppearanceResult:
    """Fit the texture and light of ``capture`` and write them to ``out`` (module docstring).

    ``tracked``: the tracking stage's folder (meshes and Gaussian colours; needed with
    ``config.meshes == "tracked"``); ``lighting``: the studio's lights for ``config.light ==
    "studio"`` (default ``ground_truth/lighting.json``); ``progress``: anything
    :func:`physavatar.progress.resolve` accepts."""
    return fit_appearance(capture, out, config, tracked=tracked, lighting=lighting, progress=progress)
