"""What this machine has free, for the up-front checks that refuse work which cannot fit.

``simulate`` (particle count), ``mesh`` (marching-cubes cells) and ``render`` (pixels) estimate
their memory before they start and refuse, in one line, what would not fit in
:data:`MEMORY_HEADROOM` of the memory free now.
"""

from __future__ import annotations

import os
from pathlib import Path

#: Share of the free memory a stage may plan to use (the rest is left to the system and other work).
MEMORY_HEADROOM = 0.8


def cache_dir(kind: str) -> Path:
    """Where derived data of one ``kind`` is kept between runs (``sdf``: obstacles' signed-distance grids;
    ``terrain``: terrain meshes): ``$WHITECAP_CACHE/kind``, by default ``~/.cache/whitecap/kind``. Each entry is
    keyed by its sources' content, so a stale one is never read, and the whole folder may be deleted at any time."""
    return Path(os.environ.get("WHITECAP_CACHE", Path.home() / ".cache" / "whitecap")) / kind


def available_memory() -> int:
    """Bytes of memory free for new work (Linux MemAvailable); very large when unknown."""
    try:
        with open("/proc/meminfo") as fh:
            for line in fh:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    return 1 << 62
