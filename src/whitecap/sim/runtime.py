"""Taichi runtime selection. One runtime per process, CPU by default.

Never Vulkan for compute: lavapipe (the software Vulkan on machines without a
GPU) silently truncates long loops, so ``auto`` means CUDA if present else CPU.
"""

from __future__ import annotations

import ctypes
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


def empty_ndarray(dtype, shape, vec: int = 0):
    """A Taichi ndarray of ``shape`` (of ``vec``-vectors where ``vec``), its memory left as the allocator
    hands it over: for arrays whose rows are always written before they are read. ``ti.ndarray`` fills every
    array with zeros on the calling thread as it makes it: the foam stage's neighbour lists (37 MB at 100k
    fluid particles) took 13-16 ms to make, against 0.3 ms unfilled and 7-9 ms for the kernel that then
    writes them on every core (the pages are first touched there, in parallel). Taichi 1.7 has no public
    option for this, so the array is built as its own constructors build it, through the same call with
    zero_fill off; should that call ever change, a zero-filled ``ti.ndarray`` is made instead."""
    shape = tuple(int(s) for s in shape) if isinstance(shape, (tuple, list)) else (int(shape),)
    try:
        from taichi._lib import core as ti_core
        from taichi.lang import impl
        from taichi.lang._ndarray import Ndarray, ScalarNdarray
        from taichi.lang.enums import Layout
        from taichi.lang.matrix import VectorNdarray, _type_factory
        from taichi.lang.util import cook_dtype

        prog, cooked = impl.get_runtime().prog, cook_dtype(dtype)
        if vec:
            element = _type_factory.get_tensor_type((vec,), cooked)
            arr = prog.create_ndarray(cook_dtype(element), shape, Layout.AOS, zero_fill=False,
                                      dbg_info=ti_core.DebugInfo(""))
            v = VectorNdarray.__new__(VectorNdarray)
            Ndarray.__init__(v)
            v.n, v.dtype, v.layout, v.shape, v.element_type, v.arr = vec, cooked, Layout.AOS, shape, element, arr
            return v
        arr = prog.create_ndarray(cooked, shape, layout=Layout.NULL, zero_fill=False, dbg_info=ti_core.DebugInfo(""))
        a = ScalarNdarray.__new__(ScalarNdarray)
        Ndarray.__init__(a)
        a.dtype, a.arr, a.shape, a.element_type = cooked, arr, tuple(arr.shape), dtype
        return a
    except (ImportError, AttributeError, TypeError):
        return ti.Vector.ndarray(vec, dtype, shape) if vec else ti.ndarray(dtype, shape)


_LIBCUDA: object = None  # libcuda through ctypes, once looked up (False: not to be had)


def _cuda_driver():
    """libcuda through ctypes where Taichi runs on CUDA and its context is current on this thread, else None."""
    global _LIBCUDA
    if _ARCH != "cuda":
        return None
    if _LIBCUDA is None:
        try:
            lib = ctypes.CDLL("libcuda.so.1")
            lib.cuMemcpyDtoH_v2.argtypes = [ctypes.c_void_p, ctypes.c_uint64, ctypes.c_size_t]
            lib.cuMemcpyHtoD_v2.argtypes = [ctypes.c_uint64, ctypes.c_void_p, ctypes.c_size_t]
            _LIBCUDA = lib
        except (OSError, AttributeError):
            _LIBCUDA = False
    if _LIBCUDA is False:
        return None
    ctx = ctypes.c_void_p()
    if _LIBCUDA.cuCtxGetCurrent(ctypes.byref(ctx)) != 0 or not ctx.value:  # type: ignore[attr-defined]
        return None
    return _LIBCUDA


def device_idle() -> bool:
    """Wait until the device has run every kernel launched so far, letting other Python threads run meanwhile;
    True where it waited (CUDA), False where there is nothing to wait for (the CPU: a kernel is done when its
    launch returns).

    Taichi's own waits (``ti.sync()``, ``to_numpy``, a kernel's return value) keep the GIL while the GPU works,
    so the background writer's thread stood still for as long as the solver's frame took on an H100 (its
    files were then written between the loop's calls, in 5 ms turns). The driver's cuCtxSynchronize, called
    through ctypes (which lets go of the GIL for a foreign call), waits on the same context (the one Taichi
    made current on this thread); the wait that follows it finds the device idle and returns at once. Where
    libcuda or a current context cannot be had, nothing is waited for and Taichi's own waits hold as before."""
    lib = _cuda_driver()
    return lib is not None and lib.cuCtxSynchronize() == 0  # type: ignore[attr-defined]


def rows_to_host(*pairs) -> bool:
    """Copy each (host array, Taichi ndarray) pair's leading bytes, as many as the host array holds, from the GPU
    with the CUDA driver (cuMemcpyDtoH through ctypes, the GIL let go); False, copying nothing, where that cannot
    be done (the CPU, no libcuda): the caller then reads the rows with its own kernel.

    Why not a Taichi kernel or ``to_numpy``: Taichi 1.7's CUDA launcher copies every host array handed to a
    kernel to the device before the launch and back after it, whether the kernel reads it or not, with the GIL
    held throughout. A frame's read-back (1 M fluid particles, 2.5 M diffuse particles: 120 MB) then crossed the
    bus twice while the background writer's thread stood still. The rows of an ndarray lie at the start of its
    allocation (``Program.get_ndarray_data_ptr_as_int``: the device pointer on CUDA), so one copy each suffices.
    The device's work so far is waited for first (as :func:`device_idle`), the GIL let go then too."""
    return _copy_rows(pairs, to_host=True)


def rows_to_device(*pairs) -> bool:
    """Copy each (Taichi ndarray, host array) pair's host array into the leading bytes of the ndarray with the CUDA
    driver (cuMemcpyHtoD, the GIL let go); False, copying nothing, where that cannot be done (the CPU, where a kernel
    reads a host array in place). As :func:`rows_to_host`, without Taichi's copy back of the host array after a
    launch; after the device's work so far, which may still read the ndarray."""
    return _copy_rows([(host, nd) for nd, host in pairs], to_host=False)


def _copy_rows(pairs, to_host: bool) -> bool:
    lib = _cuda_driver()
    if lib is None:
        return False
    lib.cuCtxSynchronize()  # type: ignore[attr-defined]  # the kernels before, on any stream, done (GIL let go)
    from taichi.lang import impl

    prog = impl.get_runtime().prog
    for host, nd in pairs:
        if not host.flags.c_contiguous or host.nbytes > nd.arr.nelement() * nd.arr.element_size():
            raise ValueError(f"a host array of {host.nbytes} bytes for an ndarray of {nd.shape}")
        if not host.nbytes:
            continue
        dev = prog.get_ndarray_data_ptr_as_int(nd.arr)
        if to_host:
            failed = lib.cuMemcpyDtoH_v2(host.ctypes.data, dev, host.nbytes)
        else:
            failed = lib.cuMemcpyHtoD_v2(dev, host.ctypes.data, host.nbytes)
        if failed:
            way = "back from" if to_host else "to"
            raise WhitecapError(f"copying {host.nbytes} bytes {way} the GPU failed (CUDA error {failed})")
    return True
