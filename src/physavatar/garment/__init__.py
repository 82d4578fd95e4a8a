"""Simulation-ready garment templates: sewing patterns fitted to an Anny body (docs/garments.md)."""

from .garment import (GARMENTS, MIN_CLEARANCE, Attachment, Garment, attachment_normals, attachment_positions, combine_template,
                      garment_skinning_weights, keep_clear, make_attachment, make_garment)
from .unfold import unfold_targets

__all__ = ["GARMENTS", "MIN_CLEARANCE", "Attachment", "Garment", "attachment_normals", "attachment_positions", "combine_template",
           "garment_skinning_weights", "keep_clear", "make_attachment", "make_garment", "unfold_targets"]
