"""The foreign-capture generator (issue 22 part 1) and the independent cloth simulator driver.

Benchmark tools, not part of the package: they share as little as possible with physavatar (its
simulator, garment designs, textures and studio lights are not used). What they do use from it:
the Anny body model (a non-default phenotype), the capture file writers and the Mitsuba renderer.

- ``newton_cloth``: NVIDIA Newton's vertex block descent (VBD) cloth solver on a moving body mesh
  (penalty contact; Newton's own Neo-Hookean membrane and dihedral-angle bending).
- ``garments``: a flared skirt and a fitted top built procedurally around the body.
- ``capture``: textures, cameras, lights, and the writer of a capture folder with ground truth.
"""
