"""physavatar: physics-aware 3D avatars of dressed people from multi-view video.

An implementation of PhysAvatar (Zheng et al., ECCV 2024) that runs on a laptop CPU. See
DESIGN.md / docs/ for the data flow: capture -> track -> fit-physics / fit-appearance -> avatar
-> animate -> render / export, with evaluation against synthetic ground truth.
"""

__version__ = "0.1.0"
