"""Taichi runtime selection. One runtime per process, CPU by default.

Never Vulkan for compute: lavapipe (the software Vulkan on machines without a
GPU) silently truncates long loops, so ``auto`` means CUDA if present else CPU.
"""

from __future__ import annotations

import ctypes
import gc
import os
import threading
from concurrent.futures import Future
from typing import Callable

import taichi as ti

from ..config import ARCHES, DEFAULT_ARCH
from ..errors import WhitecapError
from ..io.threads import process_pool

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
    if want == "cuda":
        _free_on_any_thread()
    return want


_CONTEXT: ctypes.c_void_p | None = None  # the CUDA context Taichi made current on the thread that started it
_THREAD = threading.local()  # .has_context: this thread has had that context made current


def _free_on_any_thread() -> None:
    """Let Taichi's arrays be freed on any thread, not only the one that started Taichi on CUDA.

    A Taichi ndarray frees its device memory in ``__del__`` (cuMemFreeAsync, in the CUDA context current on the
    calling thread). Python's cyclic garbage collector runs on whichever thread happens to allocate when a
    collection falls due: on an H100, ``simulate`` at 1 M particles was aborted by the driver
    (CUDA_ERROR_INVALID_CONTEXT, then SIGABRT) when a collection started in the background writer's thread,
    which has no context, and found an ndarray among the garbage. So when a collection starts on a thread that
    has not had Taichi's context made current, it is made current there first (cuCtxSetCurrent through ctypes,
    once per thread); the free is then ordered on Taichi's stream as on the main thread. The GIL, held
    throughout a collection and by every call into Taichi, keeps Taichi's own bookkeeping single-threaded."""
    global _CONTEXT
    lib = _cuda_driver()
    if lib is None:  # (no libcuda, or no context current here)
        return
    _CONTEXT = _current_context(lib)
    _THREAD.has_context = True
    if _context_for_collection not in gc.callbacks:
        gc.callbacks.append(_context_for_collection)


def _context_for_collection(phase: str, info: dict) -> None:
    """gc callback: before a collection on a thread without Taichi's CUDA context, make it current there."""
    lib = _LIBCUDA  # (at the interpreter's exit it may already be gone: then nothing is done)
    if phase != "start" or _CONTEXT is None or not lib or getattr(_THREAD, "has_context", False):
        return
    _THREAD.has_context = lib.cuCtxSetCurrent(_CONTEXT) == 0  # type: ignore[union-attr,attr-defined]


def current() -> str | None:
    return _ARCH


def on_gpu() -> bool:
    """Whether Taichi runs on a GPU (CUDA) in this process; False on the CPU and before :func:`init`."""
    return _ARCH == "cuda"


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
            lib.cuMemcpyDtoHAsync_v2.argtypes = [ctypes.c_void_p, ctypes.c_uint64, ctypes.c_size_t, ctypes.c_void_p]
            lib.cuStreamCreate.argtypes = [ctypes.POINTER(ctypes.c_void_p), ctypes.c_uint]
            lib.cuStreamSynchronize.argtypes = [ctypes.c_void_p]
            lib.cuCtxSetCurrent.argtypes = [ctypes.c_void_p]
            _LIBCUDA = lib
        except (OSError, AttributeError):
            _LIBCUDA = False
    if _LIBCUDA is False or _current_context(_LIBCUDA) is None:
        return None
    return _LIBCUDA


def _current_context(lib) -> ctypes.c_void_p | None:
    """The CUDA context current on this thread (cuCtxGetCurrent), or None."""
    ctx = ctypes.c_void_p()
    return ctx if lib.cuCtxGetCurrent(ctypes.byref(ctx)) == 0 and ctx.value else None


def device_idle() -> bool:
    """Wait until the device has run every kernel launched so far, letting other Python threads run meanwhile;
    True where it waited (CUDA), False where there is nothing to wait for (the CPU: a kernel is done when its
    launch returns).

    Taichi's own waits (``ti.sync()``, ``to_numpy``, a kernel's return value) keep the GIL while the GPU works,
    so the background writer's thread stood still for as long as the solver's frame took on an H100 (its
    files were then written between the loop's calls, in 5 ms turns). The driver's wait (_kernels_done), called
    through ctypes (which lets go of the GIL for a foreign call), waits for the same kernels (in the context Taichi
    made current on this thread); the wait that follows it finds them done and returns at once. Where libcuda or
    a current context cannot be had, nothing is waited for and Taichi's own waits hold as before."""
    lib = _cuda_driver()
    return lib is not None and _kernels_done(lib) == 0


def _kernels_done(lib) -> int:
    """Wait for every kernel Taichi launched so far (0, or the CUDA error). Taichi 1.7 launches each kernel on the
    context's legacy default stream (cuLaunchKernel with a null stream), so cuStreamSynchronize on that stream waits
    for them alone: not for a read-back still running on its non-blocking stream (rows_to_host_later), which
    cuCtxSynchronize, used before 2026-11-28, waited for too, so that the next frame's first wait held up for the
    last frame's diffuse copy (FoamGenerator.step)."""
    return lib.cuStreamSynchronize(None)  # type: ignore[no-any-return]


#: Page-lock the host arrays frames are read back into (io.array_pool's blocks, cuMemHostRegister), so that the
#: driver copies into them by DMA instead of through its own staging buffer (a block the driver will not take stays
#: pageable). Measured on an H200 (2026-11-28, benchmarks/RESULTS.md): `simulate` with foam at 1 M particles took
#: 133 ms a frame pinned against 155 and 138 pageable (the solver's steps 77 ms against 85 and 81, the loop's output
#: 17 against 26 and 24); frames byte-identical either way (tests/test_gpu.py). ``bench_simulate_foam.py --pin``
#: runs foam on once more with the other setting.
PIN_READBACK = True


def host_pinning() -> tuple[Callable[[int, int], bool] | None, Callable[[int], None] | None]:
    """(pin, unpin) for io.array_pool.ArrayPool where PIN_READBACK is on and Taichi runs on CUDA, else (None, None).
    pin(address, bytes): cuMemHostRegister, True where the driver took it; unpin(address): cuMemHostUnregister, on
    whichever thread frees the block (Taichi's context made current there first)."""
    lib = _cuda_driver() if PIN_READBACK else None
    if lib is None:
        return None, None
    try:
        lib.cuMemHostRegister_v2.argtypes = [ctypes.c_void_p, ctypes.c_size_t, ctypes.c_uint]  # type: ignore[attr-defined]
        lib.cuMemHostUnregister.argtypes = [ctypes.c_void_p]  # type: ignore[attr-defined]
    except AttributeError:  # a driver without them: pageable, as with PIN_READBACK off
        return None, None

    def pin(address: int, nbytes: int) -> bool:
        return lib.cuMemHostRegister_v2(address, nbytes, 0) == 0  # type: ignore[attr-defined]

    def unpin(address: int) -> None:
        if _current_context(lib) is None and _CONTEXT is not None:
            lib.cuCtxSetCurrent(_CONTEXT)  # type: ignore[attr-defined]
        lib.cuMemHostUnregister(address)  # type: ignore[attr-defined]

    return pin, unpin


def copies_rows() -> bool:
    """Whether :func:`rows_to_host` and :func:`rows_to_device` copy here (CUDA, with libcuda and Taichi's context
    current on this thread): a caller that must lay out a device array to copy from (rather than have a kernel
    write a host array in place, as on the CPU) asks first."""
    return _cuda_driver() is not None


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


def rows_to_host_later(*pairs, then: Callable[[], None] | None = None) -> Future | None:
    """As :func:`rows_to_host`, but the copies are made by a thread of their own, on a CUDA stream of their own,
    while this thread goes on launching kernels: returns the Future of the copies (its result: True, once every
    host array holds its rows and ``then``, if given, has run on that thread), or None, copying nothing, where
    that cannot be done (the CPU, no libcuda). The device's work so far is waited for before the copies are
    handed over, so they read what it wrote; the caller must not write those ndarrays, nor read the host arrays,
    before the Future is done. Each ndarray is kept alive by the copy until it is done.

    Why: a frame's diffuse particles (2.5 M at 1 M fluid particles, about 110 MB) took about 20 ms to come back
    over the bus into fresh host pages, the foam stage's largest share on an H100 (issue 31). The stream is made
    non-blocking (CU_STREAM_NON_BLOCKING), so the copies never wait for, nor hold up, the kernels Taichi launches
    on its own stream meanwhile: the next frame's solver steps."""
    lib = _cuda_driver()
    if lib is None:
        return None
    ctx = _current_context(lib)  # (there is one: _cuda_driver found it)
    jobs = _device_rows(lib, pairs)
    return process_pool("whitecap-readback", 1).submit(_copy_later, lib, ctx, jobs, then)


#: CU_STREAM_NON_BLOCKING (cuda.h): the stream's work does not wait for the legacy default stream's, nor it for this
_STREAM_NON_BLOCKING = 1
_STREAMS: dict[int, ctypes.c_void_p] = {}  # the read-back thread's stream by CUDA context (only it uses them)


def _copy_later(lib, ctx, jobs, then) -> bool:
    """On the read-back thread: each job's copy on this thread's stream of ``ctx``, then ``then``."""
    if lib.cuCtxSetCurrent(ctx) != 0:
        raise WhitecapError("reading back from the GPU failed: its context could not be made current")
    stream = _STREAMS.get(ctx.value)
    if stream is None:
        stream = ctypes.c_void_p()
        if lib.cuStreamCreate(ctypes.byref(stream), _STREAM_NON_BLOCKING) != 0:
            raise WhitecapError("reading back from the GPU failed: no stream could be made")
        _STREAMS[ctx.value] = stream
    for host, dev, _nd in jobs:
        failed = lib.cuMemcpyDtoHAsync_v2(host.ctypes.data, dev, host.nbytes, stream)
        if failed:
            raise WhitecapError(f"copying {host.nbytes} bytes back from the GPU failed (CUDA error {failed})")
    failed = lib.cuStreamSynchronize(stream)
    if failed:
        raise WhitecapError(f"reading back from the GPU failed (CUDA error {failed})")
    if then is not None:
        then()
    return True


def _device_rows(lib, pairs) -> list[tuple]:
    """(host array, device pointer, ndarray) for each (host array, ndarray) pair with bytes to copy, once the
    kernels launched so far are done (_kernels_done, the GIL let go)."""
    _kernels_done(lib)
    from taichi.lang import impl

    prog = impl.get_runtime().prog
    jobs = []
    for host, nd in pairs:
        if not host.flags.c_contiguous or host.nbytes > nd.arr.nelement() * nd.arr.element_size():
            raise ValueError(f"a host array of {host.nbytes} bytes for an ndarray of {nd.shape}")
        if host.nbytes:
            jobs.append((host, prog.get_ndarray_data_ptr_as_int(nd.arr), nd))
    return jobs


def _copy_rows(pairs, to_host: bool) -> bool:
    lib = _cuda_driver()
    if lib is None:
        return False
    for host, dev, _nd in _device_rows(lib, pairs):
        if to_host:
            failed = lib.cuMemcpyDtoH_v2(host.ctypes.data, dev, host.nbytes)
        else:
            failed = lib.cuMemcpyHtoD_v2(dev, host.ctypes.data, host.nbytes)
        if failed:
            way = "back from" if to_host else "to"
            raise WhitecapError(f"copying {host.nbytes} bytes {way} the GPU failed (CUDA error {failed})")
    return True
