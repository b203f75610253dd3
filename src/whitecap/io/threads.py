"""Thread pools of this process, made on first use and kept.

Per process: a child forked by a process pool (meshing, rendering) has none of its parent's threads, so
it makes its own rather than queue work for threads that do not run there. Used by the PLY writer's parts
(io/ply.py) and the GPU read-back thread (sim/runtime.py); the Blender add-on carries this module with
io/ply.py.
"""

from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor

_POOLS: dict[tuple[int, str], ThreadPoolExecutor] = {}


def process_pool(name: str, workers: int) -> ThreadPoolExecutor:
    """This process's pool called ``name`` (its threads' name prefix), of ``workers`` threads when first made."""
    key = (os.getpid(), name)
    pool = _POOLS.get(key)
    if pool is None:  # (no lock: one a forked child inherited held would never be let go)
        for old in [k for k in _POOLS if k[0] != key[0]]:
            _POOLS.pop(old, None)  # a parent's, inherited by a forked child: its threads do not run here
        pool = _POOLS.setdefault(key, ThreadPoolExecutor(max_workers=workers, thread_name_prefix=name))
    return pool
