"""Taichi runtime selection. One runtime per process, CPU by default.

Never Vulkan for compute: lavapipe (the software Vulkan on machines without a
GPU) silently truncates long loops, so ``auto`` means CUDA if present else CPU.
"""

from __future__ import annotations

import os

import taichi as ti

from ..config import ARCHES, DEFAULT_ARCH
from ..errors import WhitecapError

_ARCH: str | None = None


def cuda_available() -> bool:
    if not _has_nvidia_device():
        return False
    try:
        from taichi._lib import core as _ti_core

        return bool(_ti_core.with_cuda())
    except Exception:
        return False


def _has_nvidia_device() -> bool:
    return os.path.exists("/dev/nvidiactl") or os.path.exists("/proc/driver/nvidia/version")


def init(arch: str = DEFAULT_ARCH) -> str:
    """Initialise Taichi once for this process; return the arch actually used."""
    global _ARCH
    if arch not in ARCHES:
        raise WhitecapError(f"--arch: expected {', '.join(ARCHES[:-1])} or {ARCHES[-1]}, got {arch!r}")
    want = "cuda" if arch == "cuda" or (arch == "auto" and cuda_available()) else "cpu"
    if arch == "cuda" and not cuda_available():
        raise WhitecapError("--arch cuda: no CUDA device found (use --arch auto to fall back to the CPU)")
    if _ARCH is not None:
        if _ARCH != want:
            raise WhitecapError(f"Taichi already runs on {_ARCH} in this process; cannot switch to {want}")
        return _ARCH
    ti.init(
        arch=ti.cuda if want == "cuda" else ti.cpu,
        default_fp=ti.f32,
        default_ip=ti.i32,
        offline_cache=True,
        log_level=ti.WARN,
        random_seed=0,
    )
    _ARCH = want
    return want


def current() -> str | None:
    return _ARCH
