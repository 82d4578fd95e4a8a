"""Which Mitsuba variant the project renders with, chosen once per process.

Mitsuba's variant is process-global state, so every module that touches ``mitsuba`` goes through
:func:`mitsuba` here instead of calling ``mi.set_variant`` itself; two stages picking different
variants would silently invalidate each other's scenes.

Order of choice: the environment variable ``PHYSAVATAR_MITSUBA_VARIANT`` if set, else
``cuda_ad_rgb`` when Dr.Jit finds a CUDA device, else ``llvm_ad_rgb`` (needs a system libLLVM
>= 16, see DESIGN.md). Only the ``*_ad_rgb`` variants are supported: the scenes use RGB textures
and the inverse-rendering stage needs automatic differentiation.
"""

from __future__ import annotations

import os

ENV_VAR = "PHYSAVATAR_MITSUBA_VARIANT"
SUPPORTED = ("llvm_ad_rgb", "cuda_ad_rgb")


def choose_variant() -> str:
    """Name of the variant :func:`mitsuba` will set (does not set it)."""
    forced = os.environ.get(ENV_VAR, "").strip()
    if forced:
        if forced not in SUPPORTED:
            raise ValueError(f"{ENV_VAR}={forced!r}: supported variants are {', '.join(SUPPORTED)}")
        return forced
    import drjit as dr

    # has_backend asks the driver without initialising a context, so a CPU-only machine does
    # not pay for (or print errors from) a failed CUDA start.
    return "cuda_ad_rgb" if dr.has_backend(dr.JitBackend.CUDA) else "llvm_ad_rgb"


def mitsuba():
    """The ``mitsuba`` module with the project's variant set (idempotent)."""
    import mitsuba as mi

    want = choose_variant()
    if mi.variant() != want:
        mi.set_variant(want)
    return mi


def variant() -> str:
    """The variant in use (sets it on first call)."""
    return mitsuba().variant()
