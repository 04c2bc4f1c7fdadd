"""The process's heap: freed frame buffers stay mapped, so a frame does not pay the kernel for them.

A frame allocates a few tens of MB of large arrays (the level-B distance tensor of a 1280 x 960 frame
alone is 16 x 480 x 640 float32, 20 MB) and frees them when it returns. glibc's malloc by default
serves such arrays with fresh ``mmap``s or trims the freed top of the heap, so memory a frame needs
beyond what the warm-up left free is first touched during that frame: ~2 us of page fault per 4 kB
page, ~17 ms of a paper frame's first estimate (8900 minor faults; warm frames: none).

``keep_mapped`` (called once by ``pipeline.warm_up``) tells malloc to keep freed memory (up to
``TRIM_MB`` at the top of the heap) and to serve arrays up to ``MMAP_MB`` from the heap, all threads
from one arena (the warm-up runs in its own thread, estimates in the server's threadpool), and
touches a reserve of ``reserve_mb`` beyond the warm-up's own peak: data loaded after the warm-up (a
bank, the frame itself) takes part of the free heap, and the first frame still finds its buffers
mapped. The cost: the process's resident memory stays at its peak (plus the reserve) instead of
shrinking between frames.

glibc only (Linux); elsewhere it does nothing and says so (returns False).
"""

from __future__ import annotations

import ctypes
import ctypes.util
import threading

import numpy as np

# mallopt parameters (glibc's malloc.h)
_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD, _M_ARENA_MAX = -1, -3, -8
MMAP_MB = 32  # glibc's own ceiling for the threshold it adapts on its own
TRIM_MB = 256
RESERVE_MB = 64  # a bank and a few decoded frames loaded after the warm-up (8900 faults: 35 MB)

_ok: bool | None = None  # malloc took the settings (None: not tried yet)
_lock = threading.Lock()


def keep_mapped(reserve_mb: float = 0.0) -> bool:
    """Keep freed heap memory mapped (settings made once per process) and make sure ``reserve_mb`` of
    it is free and touched; True when malloc took the settings."""
    global _ok
    with _lock:
        if _ok is None:
            _ok = _configure()
        if not _ok:
            return False
        if reserve_mb > 0:
            # Touched in pieces under the mmap threshold, so they come from the heap and stay in it.
            piece = (MMAP_MB << 20) // 2
            held = [np.ones(piece, np.uint8) for _ in range(max(int(reserve_mb * (1 << 20)) // piece, 1))]
            del held
        return True


def _configure() -> bool:
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        mallopt = libc.mallopt
    except (OSError, AttributeError):
        return False
    mallopt.argtypes, mallopt.restype = [ctypes.c_int, ctypes.c_int], ctypes.c_int
    return all(mallopt(param, value) == 1 for param, value in (
        (_M_ARENA_MAX, 1), (_M_MMAP_THRESHOLD, MMAP_MB << 20), (_M_TRIM_THRESHOLD, TRIM_MB << 20)))
