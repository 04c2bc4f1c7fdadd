"""A real ``uvicorn`` on a loopback port, driven with httpx: the whole flow, restarts, a kill
mid-build, ``/health`` while work is running, and two worker processes on one cache dir."""

from __future__ import annotations

import contextlib
import json
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import httpx
import numpy as np
import pytest

from service.stores import open_store
from service.vision.geometry.frames import Rx, Ry

pytestmark = pytest.mark.slow  # every test here starts uvicorn

ROOT = Path(__file__).resolve().parents[1]
GRID = {"tilt_step_deg": 15, "view_step_deg": 45}
SLOW_GRID = {"view_step_deg": 8}  # with symmetry "none": several hundred views, a build of seconds
START_WAIT_S = 60  # hang guards (not speed asserts)
BUILD_WAIT_S = 300
LEASE_S = 3  # a killed build's lease runs out this fast in these tests


class Server:
    def __init__(self, cache_dir: Path, log: Path, *, workers: int = 1, env: dict | None = None) -> None:
        with socket.socket() as s:
            s.bind(("127.0.0.1", 0))
            self.port = s.getsockname()[1]
        self.url = f"http://127.0.0.1:{self.port}"
        environment = {**os.environ, "POSE_CACHE_DIR": str(cache_dir), "POSE_TEMPLATE_GRID": json.dumps(GRID),
                       "POSE_BUILD_LEASE_S": str(LEASE_S), **(env or {})}
        self.log = open(log, "ab")  # noqa: SIM115 (closed in stop/kill)
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "uvicorn", "service.main:create_app", "--factory", "--host", "127.0.0.1",
             "--port", str(self.port), "--workers", str(workers), "--log-level", "warning"],
            cwd=ROOT, env=environment, stdout=self.log, stderr=subprocess.STDOUT, start_new_session=True)
        self.client = httpx.Client(base_url=self.url, timeout=120)
        deadline = time.monotonic() + START_WAIT_S
        while True:
            assert self.proc.poll() is None, f"uvicorn exited; see {log}"
            try:
                if self.client.get("/health").status_code == 200:
                    break
            except httpx.TransportError:
                pass
            assert time.monotonic() < deadline, f"uvicorn did not start; see {log}"
            time.sleep(0.2)

    def stop(self) -> None:
        """SIGTERM to uvicorn's pid: a graceful shutdown (the lifespan stops the build pool)."""
        self.client.close()
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(timeout=60)
            except subprocess.TimeoutExpired:
                self.kill()
        self._reap()

    def kill(self) -> None:
        """SIGKILL to the server's whole process group (uvicorn, its workers, its build processes)."""
        self.client.close()
        with contextlib.suppress(ProcessLookupError):
            os.killpg(self.proc.pid, signal.SIGKILL)
        self.proc.wait(timeout=30)
        self._reap()

    def _reap(self) -> None:
        with contextlib.suppress(ProcessLookupError):  # nothing of this server may outlive it
            os.killpg(self.proc.pid, signal.SIGKILL)
        self.log.close()


@pytest.fixture
def servers(tmp_path):
    started: list[Server] = []

    def start(**kw) -> Server:
        server = Server(tmp_path / "cache", tmp_path / "uvicorn.log", **kw)
        started.append(server)
        return server

    yield start
    for server in started:
        if not server.log.closed:
            server.kill()


def upload(client: httpx.Client, mesh: bytes, **data) -> dict:
    r = client.post("/models", files={"file": ("sprayer.stl", mesh)}, data=data)
    assert r.status_code == 202, r.text
    return r.json()


def wait_status(client: httpx.Client, mid: str, until=("ready", "failed")) -> dict:
    deadline = time.monotonic() + BUILD_WAIT_S
    while True:
        info = client.get(f"/models/{mid}").json()
        if info["status"] in until:
            return info
        assert time.monotonic() < deadline, f"model {mid} still {info['status']}"
        time.sleep(0.1)


def references(client: httpx.Client, mid: str) -> dict:
    return client.get(f"/models/{mid}/references").json()


def estimate(client: httpx.Client, mid: str, frame: tuple[bytes, dict]) -> httpx.Response:
    image, camera = frame
    return client.post(f"/models/{mid}/estimate", files={"image": ("0001.png", image)},
                       data={"camera": json.dumps(camera), "options": json.dumps({"distance_mm": 500})})


def test_upload_build_estimate_restart(servers, tmp_path, sprayer_bytes, frame):
    server = servers()
    mid = upload(server.client, sprayer_bytes, symmetry="y")["id"]
    assert wait_status(server.client, mid)["status"] == "ready"
    r = estimate(server.client, mid, frame)
    assert r.status_code == 200 and r.json()["found"] is True
    server.stop()

    server = servers()  # a restarted service still knows every model
    info = server.client.get(f"/models/{mid}").json()
    assert info["status"] == "ready" and info["n_templates"] > 0
    assert estimate(server.client, mid, frame).status_code == 200
    server.stop()
    with open_store(tmp_path / "cache") as store:
        assert store.build_count(mid) == 1


def test_health_answers_while_a_build_and_estimates_run(servers, sprayer_bytes, frame):
    server = servers()
    ready = upload(server.client, sprayer_bytes, symmetry="y")["id"]
    assert wait_status(server.client, ready)["status"] == "ready"

    building = upload(server.client, sprayer_bytes, symmetry="none", templates=json.dumps(SLOW_GRID))["id"]
    stop = threading.Event()
    lock = threading.Lock()
    in_flight = [0]  # estimate requests sent and not yet answered
    codes: list[int | str] = []

    def estimates() -> None:
        with httpx.Client(base_url=server.url, timeout=120) as c:
            while not stop.is_set():
                with lock:
                    in_flight[0] += 1
                try:
                    codes.append(estimate(c, ready, frame).status_code)
                except httpx.HTTPError as e:
                    codes.append(repr(e))
                finally:
                    with lock:
                        in_flight[0] -= 1

    def busy() -> bool:
        building_now = server.client.get(f"/models/{building}").json()["status"] in ("queued", "building")
        return building_now and in_flight[0] > 0

    threads = [threading.Thread(target=estimates) for _ in range(2)]
    for t in threads:
        t.start()
    try:
        answered_while_busy = 0
        deadline = time.monotonic() + BUILD_WAIT_S
        while answered_while_busy < 5 and time.monotonic() < deadline:
            before = busy()
            r = server.client.get("/health")
            assert r.status_code == 200 and r.json()["status"] == "ok"
            answered_while_busy += before and busy()  # the build and an estimate ran all the while
        assert answered_while_busy == 5
    finally:
        stop.set()
        for t in threads:
            t.join()
    assert codes and set(codes) == {200}
    server.stop()


def test_build_killed_mid_way_resumes_after_restart(servers, tmp_path, sprayer_bytes):
    server = servers()
    mid = upload(server.client, sprayer_bytes, symmetry="none", templates=json.dumps(SLOW_GRID))["id"]
    deadline = time.monotonic() + BUILD_WAIT_S
    while (info := server.client.get(f"/models/{mid}").json())["progress"] < 0.1:
        assert info["status"] in ("queued", "building") and time.monotonic() < deadline
        time.sleep(0.05)
    server.kill()  # the server and its build process die mid-build
    with open_store(tmp_path / "cache") as store:
        assert store.get(mid)["status"] == "building" and store.build_count(mid) == 1

    server = servers()
    info = wait_status(server.client, mid)
    assert info["status"] == "ready" and info["progress"] == 1.0 and info["n_templates"] > 0
    server.stop()
    with open_store(tmp_path / "cache") as store:
        assert store.build_count(mid) == 2  # started, killed, resumed once


def test_two_workers_share_one_cache_and_build_once(servers, tmp_path, sprayer_bytes, frame):
    server = servers(workers=2)

    def fresh_connection(fn):  # a new connection per request, so the kernel spreads them over both workers
        with httpx.Client(base_url=server.url, timeout=120) as c:
            return fn(c)

    with ThreadPoolExecutor(4) as pool:
        infos = list(pool.map(lambda _: fresh_connection(lambda c: upload(c, sprayer_bytes, symmetry="y")),
                              range(4)))
    mid = infos[0]["id"]
    assert {i["id"] for i in infos} == {mid}
    assert wait_status(server.client, mid)["status"] == "ready"
    with ThreadPoolExecutor(4) as pool:
        statuses = list(pool.map(
            lambda _: fresh_connection(lambda c: c.get(f"/models/{mid}").json()["status"]), range(12)))
        codes = list(pool.map(
            lambda _: fresh_connection(lambda c: estimate(c, mid, frame).status_code), range(6)))
    assert set(statuses) == {"ready"} and set(codes) == {200}
    server.stop()
    with open_store(tmp_path / "cache") as store:
        assert store.build_count(mid) == 1


def test_reference_photos_reach_every_worker_and_survive_a_restart(servers, sprayer_bytes, frame, paper_gt):
    """Two uvicorn workers (two processes, each with its own taught-appearance memo): a reference photo
    posted to one is taught by every worker, whichever answers; DELETE is seen by both; a restart keeps
    the photo. (The paper sprayer is plain: its photos are taught and reported, not used by the estimate,
    whose answers stay 200 and untaught; tests/test_api_references.py has a part whose photos are.)"""
    image, camera = frame
    pose = json.dumps({"R": paper_gt["R"], "t_mm": paper_gt["t_mm"]})

    def post_reference(client: httpx.Client, mid: str) -> httpx.Response:
        return client.post(f"/models/{mid}/references", files={"image": ("0001.png", image)},
                           data={"camera": json.dumps(camera), "pose": pose})

    def taught(client: httpx.Client, mid: str, n: int = 6) -> set[bool]:
        """For n requests in a row (either worker): whether the worker had taught colours from the photos,
        and an estimate still answers, judged untaught (a plain part)."""
        seen = set()
        for _ in range(n):
            listed = client.get(f"/models/{mid}/references").json()
            seen.add(listed["known_fraction"] > 0)
            r = estimate(client, mid, frame)
            assert r.status_code == 200 and "appearance" not in r.json()["verdict"]["evidence"], r.text
        return seen

    server = servers(workers=2)
    mid = upload(server.client, sprayer_bytes, symmetry="y")["id"]
    assert wait_status(server.client, mid)["status"] == "ready"
    assert taught(server.client, mid) == {False}
    assert post_reference(server.client, mid).status_code == 201
    assert taught(server.client, mid) == {True}
    assert server.client.delete(f"/models/{mid}/references").status_code == 204
    assert taught(server.client, mid) == {False}
    assert post_reference(server.client, mid).status_code == 201
    assert taught(server.client, mid) == {True}
    server.stop()

    server = servers()
    assert server.client.get(f"/models/{mid}").json()["references"] == 1
    assert server.client.get(f"/models/{mid}/references").json()["references"] == 1
    assert taught(server.client, mid, n=2) == {True}
    server.stop()


def test_a_calibration_killed_mid_way_resumes_after_restart(servers, tmp_path, lbracket):
    """The server is killed (SIGKILL) while it calibrates a painted part on its photos: the record still
    asks for the calibration, and the restarted server resumes it (once the dead one's lease has run out)
    and stores it for that photo set."""
    from tests.test_api_cell import INTRINSICS, T_CAM_OBJ, transform
    from tests.test_api_references import LBRACKET_GRID, painted_scene

    server = servers()
    r = server.client.post("/models", files={"file": ("lbracket.stl", lbracket[0])},
                           data={"symmetry": "none", "templates": json.dumps(LBRACKET_GRID)})
    mid = r.json()["id"]
    assert wait_status(server.client, mid)["status"] == "ready"
    turns = (np.eye(3), Rx(20.0), Ry(-20.0), Rx(-15.0))  # four views of the painted part: they agree
    for k, turn in enumerate(turns):
        T = T_CAM_OBJ.copy()
        T[:3, :3] = turn @ T[:3, :3]
        photo = {"image": ("ref.png", painted_scene(lbracket[1], T))}
        r = server.client.post(f"/models/{mid}/references", files=photo,
                               data={"camera": json.dumps(INTRINSICS), "pose": json.dumps(transform(T)),
                                     "calibrate": json.dumps(k == len(turns) - 1)})
        assert r.status_code == 201, r.text
    deadline = time.monotonic() + BUILD_WAIT_S
    while (listed := references(server.client, mid))["calibration_status"] != "running":
        assert listed["calibration_status"] == "queued" and time.monotonic() < deadline, listed
        time.sleep(0.01)
    server.kill()  # mid-calibration: one photo's search or more still to go
    with open_store(tmp_path / "cache") as store:
        record = store.get(mid)
        assert record["calibration_wanted"] and "calibration" not in record

    server = servers()
    while (listed := references(server.client, mid))["calibration_status"] != "calibrated":
        assert listed["calibration_status"] in ("queued", "running") and time.monotonic() < deadline, listed
        time.sleep(0.1)
    assert listed["calibrated"] is True and listed["calibration_progress"] == 1.0
    server.stop()
    with open_store(tmp_path / "cache") as store:
        assert store.get(mid)["calibration"]["references_version"] == record["references_version"]
        assert store.get(mid)["calibration"]["photos"] == len(turns)
