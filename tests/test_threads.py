"""The thread budget (vision/threads.py): one number per process, applied where the work runs."""

from __future__ import annotations

import os
import threading

import numba
import pytest

from service.vision import threads


@pytest.fixture
def restore_budget():
    yield
    threads.configure(None)


def test_the_budget_caps_numba_in_the_calling_thread_and_sizes_the_pool(restore_budget):
    threads.configure(1)
    assert threads.budget() == 1
    seen = []

    def work():
        threads.use_budget()
        seen.append(numba.get_num_threads())

    t = threading.Thread(target=work)
    t.start()
    t.join()
    assert seen == [1]
    pool = threads.background()
    assert pool is threads.background() and pool._max_workers == 1  # made once, lazily
    threads.configure(None)  # back to all cores: a new pool of that size
    assert threads.budget() == (os.cpu_count() or 1)
    assert threads.background()._max_workers == threads.budget()


def test_a_budget_under_one_thread_is_refused(restore_budget):
    with pytest.raises(ValueError):
        threads.configure(0)


def test_openmp_threads_sleep_between_kernels_unless_the_environment_says_otherwise():
    import subprocess
    import sys
    from pathlib import Path

    code = "import os, service.vision.threads; print(os.environ['OMP_WAIT_POLICY'])"
    env = {k: v for k, v in os.environ.items() if k != "OMP_WAIT_POLICY"}
    for given, expected in ((None, "PASSIVE"), ("ACTIVE", "ACTIVE")):
        e = env if given is None else env | {"OMP_WAIT_POLICY": given}
        out = subprocess.run([sys.executable, "-c", code], env=e, cwd=Path(__file__).resolve().parents[1],
                             capture_output=True, text=True, check=True)
        assert out.stdout.strip() == expected
