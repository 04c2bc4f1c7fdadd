"""The heap keeps freed frame buffers mapped after ``memory.keep_mapped`` (``pipeline.warm_up`` calls it):
allocating a buffer the size of a distance tensor again touches no new page."""

from __future__ import annotations

import resource
import sys

import numpy as np
import pytest

from service.vision import memory

TENSOR_BYTES = 16 * 480 * 640 * 4  # a 1280 x 960 frame's level-B distance tensor: 4800 pages of 4 kB
MAX_NEW_PAGES = 100  # the allocator's own bookkeeping, not the buffer


def _faults() -> int:
    return resource.getrusage(resource.RUSAGE_THREAD).ru_minflt


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's mallopt")
def test_a_freed_frame_buffer_stays_mapped():
    assert memory.keep_mapped(memory.RESERVE_MB)
    a = np.ones(TENSOR_BYTES, np.uint8)  # touched once ...
    del a
    before = _faults()
    b = np.full(TENSOR_BYTES, 7, np.uint8)  # ... and again: the same memory, no page fault
    assert _faults() - before < MAX_NEW_PAGES
    # the reserve: a buffer the warm-up never made finds touched memory too
    before = _faults()
    c = np.full(TENSOR_BYTES, 3, np.uint8)
    assert _faults() - before < MAX_NEW_PAGES
    assert int(b[-1]) + int(c[0]) == 10
