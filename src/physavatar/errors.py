"""The one error type users see: a file and what is wrong with it.

The CLI turns a :class:`PhysavatarError` into one line on stderr and exit code 2 (never a
traceback), so every check of user input raises it with the offending path.
"""

from __future__ import annotations

from pathlib import Path


class PhysavatarError(Exception):
    """Bad input: ``path`` names the file (or folder) and ``problem`` says what is wrong."""

    def __init__(self, path: str | Path | None, problem: str):
        self.path = None if path is None else Path(path)
        self.problem = problem
        super().__init__(f"{self.path}: {problem}" if self.path is not None else problem)

    def __reduce__(self):  # so that it crosses process boundaries (physavatar.parallel) intact
        return (self.__class__, (self.path, self.problem))


class CaptureError(PhysavatarError):
    """A capture folder that does not follow docs/capture-format.md."""
