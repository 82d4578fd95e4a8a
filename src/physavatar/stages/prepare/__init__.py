"""``physavatar prepare``: masks, first-frame mesh, body, segmentation, boundary, UVs (docs/prepare.md)."""

from .config import PrepareConfig
from .stage import run

__all__ = ["PrepareConfig", "run"]
