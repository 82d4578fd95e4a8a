"""Capture formats in: ``physavatar import SRC OUT [--format ...]`` (docs/import.md).

One module per format reads its own files into a :class:`~.common.Source`;
:func:`~.write.write_capture` turns it into a capture folder (docs/capture-format.md) with
frame selection, undistortion, resizing and world placement, atomically.
"""

from __future__ import annotations

from pathlib import Path

from ..errors import PhysavatarError
from . import actorshq, dress4d, easymocap, nerfstudio, pose2sim
from .common import ImportOptions, Source
from .write import ImportResult, write_capture

# Detection order: the most specific files first.
FORMATS = {
    "actorshq": actorshq,
    "4d-dress": dress4d,
    "easymocap": easymocap,
    "nerfstudio": nerfstudio,
    "pose2sim": pose2sim,
}
CLUES = {
    "actorshq": "calibration.csv",
    "4d-dress": "Capture/cameras.pkl",
    "easymocap": "intri.yml + extri.yml",
    "nerfstudio": "transforms.json",
    "pose2sim": "a .toml calibration (here or in calibration/)",
}


def detect_format(src: str | Path) -> str:
    """The format of ``src`` from the files it holds."""
    src = Path(src)
    if not src.exists():
        raise PhysavatarError(src, "source not found")
    for name, module in FORMATS.items():
        if module.detect(src):
            return name
    raise PhysavatarError(src, "cannot tell the format: found none of " + "; ".join(f"{CLUES[n]} ({n})" for n in FORMATS)
                          + "; pass --format")


def read_source(src: str | Path, format: str | None = None, options: ImportOptions | None = None) -> Source:
    src = Path(src)
    options = options or ImportOptions()
    if not src.exists():
        raise PhysavatarError(src, "source not found")
    fmt = format or detect_format(src)
    if fmt not in FORMATS:
        raise PhysavatarError(None, f"option --format: {fmt!r} is not one of {', '.join(FORMATS)}")
    module = FORMATS[fmt]
    return module.read(src, options) if fmt in ("easymocap", "pose2sim") else module.read(src)


def import_capture(src: str | Path, out: str | Path, *, format: str | None = None,
                   options: ImportOptions | None = None, progress=None) -> ImportResult:
    """Read ``src`` (a dataset folder in ``format``, guessed when None) and write the capture ``out``."""
    options = options or ImportOptions()
    options.check()
    return write_capture(read_source(src, format, options), out, options, progress)


__all__ = ["FORMATS", "ImportOptions", "ImportResult", "detect_format", "import_capture", "read_source"]
