"""Template builds: bounded in faces and memory, ended by a DELETE, never flipped back from ready, and
never outliving the service that started them (issue "Reliability", items 1, 2, 10 and 11)."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import textwrap
import time
import warnings
from pathlib import Path

import pytest
import trimesh

from service.decode import TEMPLATE_FACE_BUDGET
from service.jobs.build import register_upload
from service.jobs.local import Builder
from service.main import create_app
from service.settings import Settings
from service.stores import open_store
from tests.api_helpers import wait_built
from tests.processes import alive

with warnings.catch_warnings():
    warnings.filterwarnings("ignore", message="Using `httpx` with `starlette.testclient`")
    from fastapi.testclient import TestClient

ROOT = Path(__file__).resolve().parents[1]
SMALL_GRID = {"tilt_step_deg": 15, "view_step_deg": 45}
SLOW_GRID = {"view_step_deg": 4}  # with symmetry "none": ~2,500 views, a build of a minute or more
WAIT_S = 60  # hang guards, not speed asserts


def _until(condition, what: str, wait_s: float = WAIT_S):
    deadline = time.monotonic() + wait_s
    while time.monotonic() < deadline:
        value = condition()
        if value:
            return value
        time.sleep(0.05)
    raise AssertionError(f"still waiting for {what} after {wait_s} s")



def _stl(mesh: trimesh.Trimesh) -> bytes:
    return mesh.export(file_type="stl")


def test_a_mesh_over_the_face_budget_is_simplified_before_its_build(tmp_path):
    """Item 1: the bank (what every build renders and every estimate reads) has at most the budget's
    faces, and the part keeps its size."""
    sphere = trimesh.creation.uv_sphere(40.0, count=[160, 160])
    assert len(sphere.faces) > TEMPLATE_FACE_BUDGET
    settings = Settings(cache_dir=tmp_path / "cache", template_grid=SMALL_GRID)
    with TestClient(create_app(settings)) as c:
        r = c.post("/models", files={"file": ("ball.stl", _stl(sphere))})
        assert r.status_code == 202, r.text
        info = wait_built(c, r.json()["id"])
        assert info["status"] == "ready", info
        bank = c.app.state.store.bank(info["id"])
    assert len(bank.faces) <= TEMPLATE_FACE_BUDGET
    assert bank.extents_mm == pytest.approx([80.0, 80.0, 80.0], rel=0.01)


def test_a_build_over_its_memory_cap_fails_with_a_sentence(tmp_path, sprayer_bytes):
    """Item 1: a build that would need more memory than POSE_BUILD_MEMORY_MB fails (the host keeps its
    memory); 16,000 x 16,000 supersampled renders need ~2 GB, the cap here is 1.5 GB."""
    settings = Settings(cache_dir=tmp_path / "cache", build_memory_mb=1536)
    with TestClient(create_app(settings)) as c:
        r = c.post("/models", files={"file": ("sprayer.stl", sprayer_bytes)},
                   data={"symmetry": "y", "templates": json.dumps({"render_px": 2000, "supersample": 8})})
        info = wait_built(c, r.json()["id"])
    assert info["status"] == "failed", info
    assert "POSE_BUILD_MEMORY_MB" in info["error"] and info["error"].endswith(".")


def test_delete_during_a_build_ends_its_process(tmp_path, sprayer_bytes):
    """Item 2: DELETE kills the running build process at once (its memory goes with it) instead of
    letting it run until its next progress write; the model stays deleted."""
    settings = Settings(cache_dir=tmp_path / "cache")
    with TestClient(create_app(settings)) as c:
        r = c.post("/models", files={"file": ("sprayer.stl", sprayer_bytes)},
                   data={"symmetry": "none", "templates": json.dumps(SLOW_GRID)})
        mid = r.json()["id"]
        builder = c.app.state.builder
        pid = _until(lambda: builder.running().get(mid), "the build process")
        _until(lambda: c.get(f"/models/{mid}").json()["status"] == "building", "the build to start")
        assert c.delete(f"/models/{mid}").status_code == 204
        _until(lambda: mid not in builder.running() and not alive(pid), "the build process to end", 10)
        assert c.get(f"/models/{mid}").status_code == 404
        store = c.app.state.store
        assert store.mesh(mid) is None and store.lock_holder(mid) is None


def test_a_delete_by_another_process_ends_the_build_by_itself(tmp_path, sprayer_bytes):
    """Item 2, several service processes: the one that answers the DELETE is not the build's parent;
    the build process notices the record is gone and exits."""
    settings = Settings(cache_dir=tmp_path / "cache")
    with open_store(settings.cache_dir) as store:
        rec, _ = register_upload(store, settings, sprayer_bytes, filename="sprayer.stl", symmetry="none",
                                 templates=SLOW_GRID)
        builder = Builder(settings)
        try:
            builder.submit(rec["id"])
            pid = _until(lambda: builder.running().get(rec["id"]), "the build process")
            _until(lambda: store.get(rec["id"])["status"] == "building", "the build to start")
            with open_store(settings.cache_dir) as other_process:
                assert other_process.delete(rec["id"])
            _until(lambda: not builder.running() and not alive(pid), "the build process to exit", 10)
            assert store.get(rec["id"]) is None
        finally:
            builder.shutdown()


# A build process whose SIGTERM (a stopping service) arrives right after it wrote "ready".
_STOP_AFTER_READY = textwrap.dedent("""
    import os, signal, sys, time
    sys.path.insert(0, {root!r})
    from service.jobs.build import run_build
    from service.stores.base import Store
    from service.stores import open_store

    real_update = Store.update

    def update(self, mid, **fields):
        rec = real_update(self, mid, **fields)
        if fields.get("status") == "ready":
            os.kill(os.getpid(), signal.SIGTERM)  # the service stops now, as the build finishes
            time.sleep(0.5)  # the SIGTERM handler runs, the watch thread sees it
        return rec

    Store.update = update
    print(run_build({cache!r}, {mid!r}, 30.0))
""")


def test_a_stop_right_after_the_build_finished_leaves_it_ready(tmp_path, sprayer_bytes):
    """Item 10: the watch thread's "back to queued" on SIGTERM must not overwrite the "ready" the build
    just wrote (it did: the model was rebuilt at the next start and clients got 409 meanwhile)."""
    settings = Settings(cache_dir=tmp_path / "cache", template_grid=SMALL_GRID)
    with open_store(settings.cache_dir) as store:
        rec, _ = register_upload(store, settings, sprayer_bytes, filename="sprayer.stl", symmetry="y")
    code = _STOP_AFTER_READY.format(root=str(ROOT), cache=str(settings.cache_dir), mid=rec["id"])
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert proc.returncode in (0, 128 + signal.SIGTERM), proc.stderr
    with open_store(settings.cache_dir) as store:
        assert store.get(rec["id"])["status"] == "ready"
        assert store.bank(rec["id"]) is not None and store.unfinished() == []


# A service process that starts a slow build, says the build's pid, and waits to be killed.
_SERVICE = textwrap.dedent("""
    import sys, time
    sys.path.insert(0, {root!r})
    from service.jobs.local import Builder
    from service.settings import Settings

    builder = Builder(Settings(cache_dir={cache!r}))
    builder.submit({mid!r})
    while not builder.running():
        time.sleep(0.05)
    print(builder.running()[{mid!r}], flush=True)
    time.sleep(600)
""")


def test_a_build_process_ends_with_its_killed_service_and_puts_its_model_back(tmp_path, sprayer_bytes):
    """Item 11: after kill -9 of the service, its build process does not live on (it did, holding its
    memory and the lease); the model is back in the queue, lease released, for the next start."""
    settings = Settings(cache_dir=tmp_path / "cache")
    with open_store(settings.cache_dir) as store:
        rec, _ = register_upload(store, settings, sprayer_bytes, filename="sprayer.stl", symmetry="none",
                                 templates=SLOW_GRID)
        mid = rec["id"]
        code = _SERVICE.format(root=str(ROOT), cache=str(settings.cache_dir), mid=mid)
        service = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True)
        try:
            worker = int(service.stdout.readline())
            _until(lambda: store.get(mid)["status"] == "building", "the build to start")
            service.kill()
            service.wait(timeout=30)
            _until(lambda: not alive(worker), "the orphaned build process to exit", 10)
        finally:
            service.kill()
            service.stdout.close()
        assert store.get(mid)["status"] == "queued"
        assert store.lock_holder(mid) is None


def test_a_flat_mesh_is_refused_at_upload_and_a_line_like_bank_fails_its_build(tmp_path):
    """Item 8: a degenerate model must not produce confident poses (nor 500s). A zero-thickness plate was
    accepted, built, and its edge-on views (lines, or fewer border points than the coarse search
    samples) made every estimate fail with a 500."""
    from service.errors import UnprocessableError
    from service.jobs.build import check_bank
    from tests.test_store import _bank

    plate = trimesh.creation.box((100.0, 60.0, 1.0)).subdivide()
    flat = trimesh.Trimesh(plate.vertices * [1.0, 1.0, 0.0], plate.faces)
    settings = Settings(cache_dir=tmp_path / "cache", template_grid=SMALL_GRID)
    with TestClient(create_app(settings)) as c:
        r = c.post("/models", files={"file": ("plate.stl", _stl(flat))}, data={"symmetry": "none"})
        assert r.status_code == 422, r.text
        assert "flat" in r.json()["detail"] and "thickness" in r.json()["detail"]
        r = c.post("/models", files={"file": ("plate.stl", _stl(trimesh.creation.box((100.0, 60.0, 3.0))))},
                   data={"symmetry": "none"})
        assert r.status_code == 202  # a thin plate with a real thickness is a part
    with pytest.raises(UnprocessableError, match="border points"):
        check_bank(_bank())  # views of 4 to 6 border points


def test_a_build_process_keeps_to_the_services_thread_budget(tmp_path, monkeypatch):
    """POSE_THREADS reaches each build process: the Builder passes it on the worker's command line and
    ``worker_main`` sets the process's budget before the build (service.vision.threads)."""
    from service.jobs import build, local
    from service.vision import threads

    commands = []

    class _Done:
        pid = 1

        def wait(self) -> int:
            return 0

    def popen(cmd, **kwargs):
        commands.append(cmd)
        return _Done()

    monkeypatch.setattr(local.subprocess, "Popen", popen)
    for budget, arg in ((1, "1"), (None, "")):
        b = Builder(Settings(cache_dir=tmp_path, threads=budget))
        b.submit("m1")
        _until(lambda b=b: not b.running(), "the fake build to end")
        assert commands.pop()[-1] == arg

    seen = []
    monkeypatch.setattr(build, "run_build", lambda *a, **k: seen.append(threads.budget()) or "ready")
    before = threads._budget
    try:
        build.worker_main([str(tmp_path), "m1", "30", str(os.getpid()), "0", "", "1"])
    finally:
        threads.configure(before)
    assert seen == [1]
