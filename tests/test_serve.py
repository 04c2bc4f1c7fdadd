"""``python -m service serve`` (the Docker image's CMD) as a real process on a loopback port: JSON
logs, SIGTERM finishing the request in flight and exiting 0, SIGTERM leaving a running build
resumable, and ``/metrics`` summed over two worker processes."""

from __future__ import annotations

import contextlib
import json
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import httpx
import numpy as np
import pytest
from prometheus_client.parser import text_string_to_metric_families

from service.stores import open_store
from tests.processes import alive
from tests.test_server import GRID, SLOW_GRID, estimate, upload, wait_status

pytestmark = pytest.mark.slow  # every test here starts `python -m service serve`

ROOT = Path(__file__).resolve().parents[1]
START_WAIT_S = 60  # hang guards, not speed asserts
STOP_WAIT_S = 60
BUILD_WAIT_S = 300
LEASE_S = 3
OPTIONS = {"distance_range_mm": [300, 900]}  # the distance searched too


def free_port() -> int:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class Serve:
    """``python -m service serve`` with the given POSE_* environment; its stdout is the JSON log."""

    def __init__(self, tmp: Path, *, workers: int = 1, env: dict[str, str] | None = None) -> None:
        self.port = free_port()
        self.url = f"http://127.0.0.1:{self.port}"
        self.log_path = tmp / f"serve-{self.port}.log"
        environment = {k: v for k, v in os.environ.items()
                       if not k.startswith("POSE_") and k != "PROMETHEUS_MULTIPROC_DIR"}
        environment.update({"POSE_CACHE_DIR": str(tmp / "cache"), "POSE_TEMPLATE_GRID": json.dumps(GRID),
                            "POSE_BUILD_LEASE_S": str(LEASE_S), "POSE_PORT": str(self.port),
                            "POSE_PLANE_CALIBRATION_SCENES": "0",
                            "POSE_WORKERS": str(workers), **(env or {})})
        with open(self.log_path, "wb") as log:
            self.proc = subprocess.Popen([sys.executable, "-m", "service", "serve"], cwd=ROOT,
                                         env=environment, stdout=log, stderr=subprocess.STDOUT,
                                         start_new_session=True)
        self.client = httpx.Client(base_url=self.url, timeout=120)
        deadline = time.monotonic() + START_WAIT_S
        while True:
            assert self.proc.poll() is None, f"serve exited:\n{self.log_path.read_text()}"
            with contextlib.suppress(httpx.TransportError):
                if self.client.get("/health").status_code == 200:
                    break
            assert time.monotonic() < deadline, f"serve did not start:\n{self.log_path.read_text()}"
            time.sleep(0.2)

    def terminate(self) -> int:
        """SIGTERM, as docker stop sends it; the exit status."""
        self.client.close()
        self.proc.send_signal(signal.SIGTERM)
        return self.proc.wait(timeout=STOP_WAIT_S)

    def log(self) -> list[dict]:
        return [json.loads(line) for line in self.log_path.read_text().splitlines() if line.strip()]

    def close(self) -> None:
        self.client.close()
        with contextlib.suppress(ProcessLookupError):  # nothing of this server may outlive the test
            os.killpg(self.proc.pid, signal.SIGKILL)
        self.proc.wait(timeout=30)


@pytest.fixture
def serve(tmp_path):
    started: list[Serve] = []

    def start(**kw) -> Serve:
        started.append(Serve(tmp_path, **kw))
        return started[-1]

    yield start
    for s in started:
        s.close()


def sample(text: str, name: str, **labels: str) -> float | None:
    for family in text_string_to_metric_families(text):
        for s in family.samples:
            if s.name == name and all(s.labels.get(k) == v for k, v in labels.items()):
                return s.value
    return None


def test_sigterm_finishes_the_estimate_in_flight_and_exits_0(serve, sprayer_bytes, frame):
    server = serve()
    mid = upload(server.client, sprayer_bytes, symmetry="y")["id"]
    assert wait_status(server.client, mid)["status"] == "ready"
    assert estimate(server.client, mid, frame).status_code == 200  # numba's kernels loaded

    # The request is held in flight by its own body: half of it is sent, the rest only once uvicorn
    # has begun to shut down (an estimate is too fast now to be caught in flight by timing).
    image, camera = frame
    request = httpx.Request("POST", f"{server.url}/models/{mid}/estimate",
                            files={"image": ("0001.png", image)},
                            data={"camera": json.dumps(camera), "options": json.dumps(OPTIONS)},
                            headers={"X-Request-ID": "in-flight-at-sigterm"})
    body = request.read()
    shutting_down = threading.Event()

    def trickle():
        yield body[: len(body) // 2]
        shutting_down.wait(STOP_WAIT_S)
        yield body[len(body) // 2:]

    answer: list[httpx.Response | Exception] = []

    def in_flight_estimate() -> None:
        headers = {k: v for k, v in request.headers.items() if k.lower() != "content-length"}
        try:
            with httpx.Client(timeout=120) as c:
                answer.append(c.post(str(request.url), content=trickle(), headers=headers))
        except Exception as e:  # reported by the assert below
            answer.append(e)

    thread = threading.Thread(target=in_flight_estimate)
    thread.start()
    deadline = time.monotonic() + START_WAIT_S
    # in progress: the estimate and this scrape itself
    while sample(server.client.get("/metrics").text, "posecell_http_requests_in_progress") < 2:
        assert time.monotonic() < deadline and not answer, answer
        time.sleep(0.05)
    server.client.close()
    server.proc.send_signal(signal.SIGTERM)
    waiting_line = "Waiting for connections to close. (CTRL+C to force quit)"
    while waiting_line not in [x["message"] for x in server.log()]:
        assert time.monotonic() < deadline and server.proc.poll() is None, "no graceful shutdown began"
        time.sleep(0.05)
    shutting_down.set()
    status = server.proc.wait(timeout=STOP_WAIT_S)
    thread.join(timeout=STOP_WAIT_S)

    assert len(answer) == 1 and isinstance(answer[0], httpx.Response), answer
    assert answer[0].status_code == 200 and answer[0].json()["found"] is True
    assert status == 0
    lines = server.log()
    messages = [x["message"] for x in lines]
    waiting = messages.index(waiting_line)
    answered = next(i for i, x in enumerate(lines) if x.get("request_id") == "in-flight-at-sigterm"
                    and x["logger"] == "service.access")
    assert waiting < answered, "the estimate was answered after the shutdown began"
    assert lines[answered]["status"] == 200 and lines[answered]["path"] == f"/models/{mid}/estimate"
    assert "Application shutdown complete." in messages[answered:]


def test_sigterm_mid_build_leaves_it_queued_and_the_next_start_resumes_it(serve, tmp_path, sprayer_bytes):
    server = serve()
    mid = upload(server.client, sprayer_bytes, symmetry="none", templates=json.dumps(SLOW_GRID))["id"]
    deadline = time.monotonic() + BUILD_WAIT_S
    while (info := server.client.get(f"/models/{mid}").json())["progress"] < 0.05:
        assert info["status"] in ("queued", "building") and time.monotonic() < deadline, info
        time.sleep(0.05)
    assert server.terminate() == 0
    with open_store(tmp_path / "cache") as store:
        record = store.get(mid)
        assert record["status"] == "queued", record  # not "building" with no one building it
        assert store.lock_holder(mid) is None and store.build_count(mid) == 1

    server = serve()  # resumes at once: no lease left to wait out
    deadline = time.monotonic() + LEASE_S + START_WAIT_S
    with open_store(tmp_path / "cache") as store:
        while store.build_count(mid) < 2:
            assert time.monotonic() < deadline, "the interrupted build was not resumed"
            time.sleep(0.05)
    assert server.terminate() == 0


def test_two_workers_report_summed_metrics_from_a_fresh_directory(serve, tmp_path):
    metrics_dir = tmp_path / "metrics"
    metrics_dir.mkdir()
    (metrics_dir / "counter_999999.db").write_bytes(b"left over from an earlier run")  # unreadable if kept
    server = serve(workers=2, env={"PROMETHEUS_MULTIPROC_DIR": str(metrics_dir)})

    def fresh(fn):  # a new connection per request, so the kernel spreads them over both workers
        with httpx.Client(base_url=server.url, timeout=60) as c:
            return fn(c)

    n = 20
    assert {fresh(lambda c: c.get("/models").status_code) for _ in range(n)} == {200}
    for _ in range(6):
        r = fresh(lambda c: c.get("/metrics"))
        assert r.status_code == 200, r.text
        total = sample(r.text, "posecell_http_requests_total", method="GET", route="/models", status="200")
        assert total == n
    assert not (metrics_dir / "counter_999999.db").exists()
    pids = {p.stem.rsplit("_", 1)[1] for p in metrics_dir.glob("gauge_livesum_*.db")}
    assert len(pids) == 2, sorted(metrics_dir.iterdir())  # both workers write to the shared directory
    assert server.terminate() == 0
    assert not list(metrics_dir.glob("gauge_livesum_*.db")), "stopped workers leave no in-progress gauge"



def _children(pid: int) -> set[int]:
    out = set()
    for stat in Path("/proc").glob("[0-9]*/stat"):
        with contextlib.suppress(OSError):
            fields = stat.read_text().split(")")[-1].split()
            if int(fields[1]) == pid:
                out.add(int(stat.parent.name))
    return out


@pytest.mark.slow
def test_kill_9_leaves_no_build_process_and_the_next_start_removes_its_metrics_dir(serve, tmp_path,
                                                                                 sprayer_bytes):
    """Issue item 11: after kill -9 of the server (only its own pid, as the OOM killer does) its build
    process and anything else it started exit by themselves, the build is resumable, and the next
    start removes the metrics directory the killed server could not remove."""
    tmp = tmp_path / "tmp"
    tmp.mkdir()
    server = serve(env={"TMPDIR": str(tmp)})
    mid = upload(server.client, sprayer_bytes, symmetry="none", templates=json.dumps(SLOW_GRID))["id"]
    deadline = time.monotonic() + BUILD_WAIT_S
    while server.client.get(f"/models/{mid}").json()["status"] != "building":
        assert time.monotonic() < deadline
        time.sleep(0.05)
    children = _children(server.proc.pid)
    assert children, "the build runs in a child process"
    server.client.close()
    server.proc.kill()
    server.proc.wait(timeout=30)
    deadline = time.monotonic() + 15
    while any(alive(p) for p in children):
        assert time.monotonic() < deadline, f"left alive: {[p for p in children if alive(p)]}"
        time.sleep(0.05)
    stale = list(tmp.glob("posecell-metrics-*"))
    assert len(stale) == 1
    with open_store(tmp_path / "cache") as store:
        assert store.get(mid)["status"] == "queued" and store.lock_holder(mid) is None

    server = serve(env={"TMPDIR": str(tmp)})
    assert not stale[0].exists()
    assert len(list(tmp.glob("posecell-metrics-*"))) == 1  # its own
    assert server.terminate() == 0
    assert not list(tmp.glob("posecell-metrics-*"))


def burn_cpu() -> subprocess.Popen:
    """A process that keeps one core busy until killed."""
    return subprocess.Popen([sys.executable, "-c", "while True: pass"], start_new_session=True)


def test_a_fresh_server_on_a_busy_machine_finds_the_paper_renders_as_an_idle_one(serve, tmp_path, data_dir,
                                                                                  sprayer_bytes):
    """Issue 45: a fresh process (an empty kernel cache of its own) beside two CPU-burning processes, with
    default options, must find the first paper renders, and with the very poses it gives them idle and
    warm: no deadline unless asked, so neither the load nor the process's past changes an answer."""
    rows = [json.loads(line) for line in (data_dir / "paper" / "gt.jsonl").read_text().splitlines()[:5]]
    burners = [burn_cpu() for _ in range(2)]
    try:
        server = serve(env={"NUMBA_CACHE_DIR": str(tmp_path / "numba")})
        mid = upload(server.client, sprayer_bytes, symmetry="y")["id"]
        assert wait_status(server.client, mid)["status"] == "ready"
        busy = [paper_estimate(server.client, mid, data_dir, row) for row in rows]
    finally:
        for b in burners:
            os.killpg(b.pid, signal.SIGKILL)
            b.wait(timeout=30)
    wait_until = time.monotonic() + BUILD_WAIT_S
    while not server.client.get("/health").json()["ready"]:
        assert time.monotonic() < wait_until, "the warm-up never ended"
        time.sleep(0.5)
    idle = [paper_estimate(server.client, mid, data_dir, row) for row in rows]
    for row, b, i in zip(rows, busy, idle, strict=True):
        assert b["found"] and not b["deadline_reached"], (row["image"], b["verdict"])
        truth = np.asarray(row["t_mm"])
        assert np.linalg.norm(np.asarray(b["refined"]["t_mm"]) - truth) < PAPER_T_TOL_MM, row["image"]
        np.testing.assert_allclose(b["refined"]["t_mm"], i["refined"]["t_mm"], atol=1e-6)
        np.testing.assert_allclose(b["refined"]["R"], i["refined"]["R"], atol=1e-9)


PAPER_T_TOL_MM = 2.0  # the refined paper poses are ~0.1 mm off; a wrong match is tens of mm off


def paper_estimate(client: httpx.Client, mid: str, data_dir: Path, row: dict) -> dict:
    K = row["K"]
    camera = {"fx": K[0][0], "fy": K[1][1], "cx": K[0][2], "cy": K[1][2]}
    r = client.post(f"/models/{mid}/estimate", files={"image": ("f.png", (data_dir / "paper" / row["image"])
                                                                 .read_bytes())},
                    data={"camera": json.dumps(camera), "options": json.dumps({"distance_mm": 500})})
    assert r.status_code == 200, r.text
    return r.json()
