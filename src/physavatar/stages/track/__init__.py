"""Mesh tracking with mesh-aligned Gaussians (PhysAvatar Sec. 3.1), on a CPU.

One flat Gaussian sits on each template face (:mod:`.gaussians`); it carries a colour (linear
RGB, composited in linear light and then sRGB-encoded, like the renderer that made the capture),
two in-plane log-scales and an opacity logit.

- Frame 1 (the template is frame 1): colours, scales and opacities are fitted, vertices fixed.
- Frames t > 1 (``prediction.init="mixed"``): the body and the garment's boundary start on the
  template skinned to the capture's body pose of frame t, the free garment on its optical-flow
  (or constant-velocity, or simulated) prediction (:mod:`.prediction`, :mod:`.flow`); the
  vertices are fitted, colours, scales and opacities stay as frame 1 left them (by default). The
  loss (:mod:`.losses`, :mod:`.fit`) is Eq. 4 plus an anchor of the skinned vertices to their pose,

      L = λ L1 + (1 - λ)(1 - SSIM)  +  w_mask |alpha - mask|  +  λ_iso L_iso  +  λ_n L_normal
          + w_anchor L_anchor  +  w_coll L_collision,

  rendered into every training camera at every step (:mod:`.views`), coarse to fine over an
  image pyramid, with Adam and early stopping on a loss plateau (docs/tracking.md gives the
  schedule and why).

Outputs (:func:`run`; settings :class:`TrackConfig`, in groups ``fit``, ``loss``, ``prediction``,
``flow``)::

    out/config.json            the exact TrackConfig, nested by group (holdout resolved to camera
                               names), and the capture's path
    out/frames/<frame>.npz     vertices [V, 3] float32, face_colors [F, 3] (linear RGB);
                               the first frame also log_scales [F, 2], opacity_logits [F], edge_index [F];
                               later frames also start_vertices, fit_vertices [V, 3] (the frame's
                               start and its fit before the final corrections, for diagnosis);
                               input_key: the content key of the capture data it was fitted
                               from (stage.frame_key)
    out/meshes/<frame>.ply     the tracked mesh with per-vertex label and boundary
    out/track_log.csv          frame, iterations, final loss terms, seconds
    out/tracked.npz            vertices [T, V, 3], faces, labels, face_colors [T, F, 3], frames, ...

Every file is written atomically; a rerun with the same config skips finished frames made from
the same capture data (the cameras, capture.json, template, body poses and the frame's images
and masks, chained over the frames before it); a frame whose data changed is tracked again, and
so is every frame after it.
"""

from .config import FitConfig, FlowConfig, LossConfig, PredictionConfig, TrackConfig, pipeline_config, second_pass_config

__all__ = ["FitConfig", "FlowConfig", "LossConfig", "PredictionConfig", "TrackConfig", "TrackResult",
           "pipeline_config", "run", "second_pass_config", "track"]


def __getattr__(name: str):
    # the stage (torch, numba, the rasterizer) loads on first use, so the CLI can read
    # TrackConfig's options without it
    if name in ("run", "track", "TrackResult"):
        from . import stage

        return getattr(stage, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
