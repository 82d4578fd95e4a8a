"""Vertex labels of a template mesh: which part of the avatar each vertex belongs to.

The body is label 0; garments are labelled 1..``MAX_LABEL`` (template/mesh.ply's ``label``
property, docs/capture-format.md).
"""

LABEL_BODY = 0
MAX_LABEL = 15  # garments are labelled 1..MAX_LABEL

__all__ = ["LABEL_BODY", "MAX_LABEL"]
