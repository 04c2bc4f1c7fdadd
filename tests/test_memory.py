"""The heap keeps freed frame buffers mapped after ``memory.keep_mapped`` (``pipeline.warm_up`` calls it):
allocating a buffer the size of a distance tensor again touches no new page. And a real server gives back
what a 100 MB upload took once its model is deleted."""

from __future__ import annotations

import resource
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import trimesh

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


# --- a large upload, then DELETE, on a real server ---------------------------------------------------

RETURNED_WITHIN_MB = 100  # issue 45: five seconds after the DELETE, within this of before the upload
SETTLE_S = 5  # the "five seconds after": time for the killed build and freed buffers to go
WARM_UP_WAIT_S = 600  # a hang guard: a first start compiles the kernels
DECODED_MB = 1000  # decoding the 100 MB STL peaks ~1.2 GB above the server's size: the server may not


def _rss_mb(pid: int, field: str = "VmRSS") -> float:
    """Resident (``VmRSS``) or peak resident (``VmHWM``) memory of process ``pid``, MiB."""
    line = next(x for x in Path(f"/proc/{pid}/status").read_text().splitlines() if x.startswith(field))
    return int(line.split()[1]) / 1024


@pytest.mark.slow
@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc")
def test_a_deleted_large_model_gives_its_memory_back(tmp_path):
    from tests.test_serve import Serve

    stl = tmp_path / "sphere.stl"  # the upload: a 100 MB binary STL of 2.0 M faces
    trimesh.creation.uv_sphere(50.0, count=[707, 707]).export(stl)
    data = stl.read_bytes()
    assert len(data) > 99e6
    server = Serve(tmp_path)
    try:
        pid = server.proc.pid
        warmed_by = time.monotonic() + WARM_UP_WAIT_S  # the warm-up's heap is part of "before"
        while not any(str(e.get("message", "")).startswith("warm-up done") for e in server.log()):
            assert time.monotonic() < warmed_by, "the server's warm-up did not end"
            time.sleep(0.2)
        before = _rss_mb(pid)
        r = server.client.post("/models", files={"file": ("sphere.stl", data)})
        assert r.status_code == 202, r.text
        uploaded, peak = _rss_mb(pid), _rss_mb(pid, "VmHWM")
        assert server.client.delete(f"/models/{r.json()['id']}").status_code == 204
        time.sleep(SETTLE_S)
        after = _rss_mb(pid)
        print(f"server RSS {before:.0f} MB before the upload, {uploaded:.0f} MB after it (peak {peak:.0f}), "
              f"{after:.0f} MB {SETTLE_S} s after the DELETE")
        assert after - before < RETURNED_WITHIN_MB
        assert peak - before < DECODED_MB  # the mesh was decoded in a process of its own
    finally:
        server.close()
