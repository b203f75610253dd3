"""What this machine has free, for the up-front checks that refuse work which cannot fit.

``simulate`` (particle count), ``mesh`` (marching-cubes cells) and ``render`` (pixels) estimate
their memory before they start and refuse, in one line, what would not fit in
:data:`MEMORY_HEADROOM` of the memory free now.
"""

from __future__ import annotations

#: Share of the free memory a stage may plan to use (the rest is left to the system and other work).
MEMORY_HEADROOM = 0.8


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
