"""An environment map as a few lights: Debevec's median-cut sampling of a light probe.

Debevec (2005), "A Median Cut Algorithm for Light Probe Sampling": split the latitude-longitude
map into regions of equal energy, each cut across the region's longer side (its width measured
on the sphere, so shrunk towards the poles) at the texel that halves its energy, and put one
directional light at each region's energy centroid carrying the region's whole radiance times
solid angle. This keeps the map's total power exactly and its diffuse shading closely, with as
few lights as a rasterizer affords. Here the region cut next is always the one with the most
energy (so any number of lights, not only powers of two), and the map's per-channel minimum is
taken out first as a constant (``Ambient``), so a map with a uniform floor is not spent on lights
that only add up to that floor.

The lights are the project's own (:class:`~.lights.Ambient`, :class:`~.lights.SunLight`), in its
units: under them a white diffuse surface of normal n receives the irradiance
π·a + Σ_k S_k max(0, n·d_k), against ∫ L(ω) max(0, n·ω) dω under the map. The viewer (three.js
lights) uses them to show a fitted environment.
"""

from __future__ import annotations

import heapq

import numpy as np

from .lights import Ambient, SunLight, envmap_directions

LUMA = np.array([0.2126, 0.7152, 0.0722])  # Rec. 709 luminance of linear RGB


def texel_solid_angles(height: int, width: int) -> np.ndarray:
    """[H, W] solid angle of each texel of an equirectangular map (they sum to 4π)."""
    t0 = np.arange(height) / height * np.pi
    band = (np.cos(t0) - np.cos(t0 + np.pi / height)) * (2 * np.pi / width)
    return np.repeat(band[:, None], width, axis=1)


def envmap_world_directions(height: int, width: int, rotation_deg: float = 0.0) -> np.ndarray:
    """[H, W, 3] world direction of each texel of a map turned ``rotation_deg`` about +z (``EnvMap``)."""
    c, s = np.cos(np.radians(rotation_deg)), np.sin(np.radians(rotation_deg))
    rz = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    return envmap_directions(height, width) @ rz.T


def median_cut_lights(image, n_lights: int = 16, *, rotation_deg: float = 0.0, scale: float = 1.0,
                      name: str = "envmap") -> list:
    """``[Ambient(floor), SunLight, ...]``: at most ``n_lights`` directional lights and the
    constant floor that together stand for the equirectangular radiance map ``image`` ([H, W, 3]
    linear, non-negative), turned and scaled as :class:`~.lights.EnvMap` does (module doc).
    Regions without energy give no light; a constant map gives the ambient light alone."""
    L = np.asarray(image, np.float64) * float(scale)
    if L.ndim != 3 or L.shape[2] != 3 or not np.isfinite(L).all() or (L < 0).any():
        raise ValueError(f"environment map must be finite, non-negative [H, W, 3], got {L.shape}")
    if n_lights < 1:
        raise ValueError(f"n_lights must be at least 1, got {n_lights}")
    H, W = L.shape[:2]
    floor = L.reshape(-1, 3).min(0)
    R = L - floor
    dw = texel_solid_angles(H, W)
    power = R * dw[..., None]  # radiance × solid angle of each texel, RGB
    energy = power @ LUMA
    dirs = envmap_world_directions(H, W, rotation_deg)
    sin_theta = np.sin((np.arange(H) + 0.5) / H * np.pi)

    def entry(r0, r1, c0, c1):
        return (-float(energy[r0:r1, c0:c1].sum()), r0, r1, c0, c1)

    heap = [entry(0, H, 0, W)]
    done = []
    while heap and len(heap) + len(done) < n_lights:
        e, r0, r1, c0, c1 = heapq.heappop(heap)
        if -e <= 0.0 or (r1 - r0 == 1 and c1 - c0 == 1):
            done.append((e, r0, r1, c0, c1))
            continue
        height = (r1 - r0) * np.pi / H  # the region's sides on the sphere: rows span π/H,
        width = (c1 - c0) * 2.0 * np.pi / W * sin_theta[r0:r1].max()  # columns 2π/W at the widest
        rows = r1 - r0 > 1 and (c1 - c0 == 1 or height >= width)
        if rows:
            cum = np.cumsum(energy[r0:r1, c0:c1].sum(1))
            k = int(np.clip(np.searchsorted(cum, cum[-1] / 2.0) + 1, 1, r1 - r0 - 1))
            heapq.heappush(heap, entry(r0, r0 + k, c0, c1))
            heapq.heappush(heap, entry(r0 + k, r1, c0, c1))
        else:
            cum = np.cumsum(energy[r0:r1, c0:c1].sum(0))
            k = int(np.clip(np.searchsorted(cum, cum[-1] / 2.0) + 1, 1, c1 - c0 - 1))
            heapq.heappush(heap, entry(r0, r1, c0, c0 + k))
            heapq.heappush(heap, entry(r0, r1, c0 + k, c1))
    out = [Ambient(tuple(float(x) for x in floor), name=f"{name}_floor")] if floor.max() > 0 else []
    for i, (_, r0, r1, c0, c1) in enumerate(sorted(heap + done, key=lambda t: t[0])):
        P = power[r0:r1, c0:c1].reshape(-1, 3)
        if P.sum() <= 0.0:
            continue
        w = energy[r0:r1, c0:c1].reshape(-1)
        d = (dirs[r0:r1, c0:c1].reshape(-1, 3) * (w if w.sum() > 0 else P.sum(1))[:, None]).sum(0)
        if np.linalg.norm(d) == 0.0:  # energy spread evenly round a pole: its mean direction
            d = dirs[r0:r1, c0:c1].reshape(-1, 3).mean(0)
        out.append(SunLight(to_sun=tuple(float(x) for x in d / np.linalg.norm(d)),
                            irradiance=tuple(float(x) for x in P.sum(0)), name=f"{name}_{i}"))
    return out
