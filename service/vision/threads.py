"""The process's thread budget: one number, set once, read by every parallel part of ``vision/``.

Parallelism stacks up in four layers: uvicorn worker processes (``POSE_WORKERS``), template-build
processes (``POSE_BUILD_WORKERS`` per service process), and inside each process numba's parallel
kernels and a pool of background threads (the refinement's second thread, a build's view renders).
This module caps the last two at ``budget()`` threads each per process (``POSE_THREADS``, default:
all cores); choose ``POSE_WORKERS x POSE_THREADS`` about the machine's cores (on 2 cores: 1 x 2, or
2 x 1 for more requests in parallel at a longer latency each).

``vision/`` cannot read the service's settings (pydantic): the service calls ``configure`` once per
process (the app's lifespan, a build process's ``builder.worker_main``, the CLI); without it the
budget is all cores. numba's thread count is per calling thread, so each entry point
(``pipeline.estimate``, ``pipeline.build_templates``) calls ``use_budget`` in the thread that runs it.
"""

from __future__ import annotations

import os
import threading
from concurrent.futures import ThreadPoolExecutor

import numba

_budget: int | None = None
_pool: ThreadPoolExecutor | None = None
_lock = threading.Lock()


def configure(threads: int | None) -> None:
    """Set this process's budget (None: all cores). A pool made under an earlier budget is replaced."""
    global _budget, _pool
    if threads is not None and threads < 1:
        raise ValueError("threads must be at least 1.")
    with _lock:
        _budget = threads
        old, _pool = _pool, None
    if old is not None:
        old.shutdown(wait=False)


def budget() -> int:
    """Threads this process may keep busy in numba kernels, and in its background pool."""
    return _budget or os.cpu_count() or 1


def use_budget() -> None:
    """Cap numba's parallel kernels started from the calling thread at the budget."""
    numba.set_num_threads(max(1, min(budget(), numba.config.NUMBA_NUM_THREADS)))


def background() -> ThreadPoolExecutor:
    """The process's pool of background threads (``budget()`` of them), made on first use."""
    global _pool
    with _lock:
        if _pool is None:
            _pool = ThreadPoolExecutor(max_workers=budget(), thread_name_prefix="vision")
        return _pool
