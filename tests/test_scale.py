"""Scale out (issue 18): the Redis store behind the API, /health while Redis is away, builds as
queue jobs taken by ``python -m service worker`` processes. Every test runs a real redis-server
(tests/redis_server.py); the slow ones start uvicorn replicas and workers as processes."""

from __future__ import annotations

import warnings

import pytest

from service.main import create_app
from service.settings import Settings
from tests.redis_server import RedisServer, redis_server_binary

with warnings.catch_warnings():  # starlette would like httpx2; the test extra installs httpx
    warnings.filterwarnings("ignore", message="Using `httpx` with `starlette.testclient`")
    from fastapi.testclient import TestClient

needs_redis = pytest.mark.skipif(redis_server_binary() is None,
                                 reason="no redis-server installed: apt-get install redis-server")
CAMERA = {"fx": 1000.0, "fy": 1000.0, "cx": 320.0, "cy": 240.0, "width": 640, "height": 480}


def test_the_store_setting_takes_only_a_redis_url():
    assert Settings(store="").store is None and Settings().store_location == "templates_cache"
    assert Settings(store="redis://h:6379/0").store_location == "redis://h:6379/0"
    with pytest.raises(ValueError, match="redis://"):
        Settings(store="/some/dir")


@needs_redis
def test_health_is_503_while_redis_is_away_and_recovers_with_nothing_lost(tmp_path):
    server = RedisServer(tmp_path / "redis").start()
    try:
        settings = Settings(store=server.url, cache_dir=tmp_path / "unused")
        with TestClient(create_app(settings)) as c:
            r = c.get("/health")
            assert r.status_code == 200 and r.json()["store"] == "redis"
            assert c.put("/cameras/cell", json=CAMERA).status_code == 201

            server.stop()
            for path in ("/health", "/models", "/cameras/cell"):
                r = c.get(path)
                assert r.status_code == 503, path
                detail = r.json()["detail"]
                assert "cannot be reached" in detail and "POSE_STORE" in detail and detail.count(".") >= 1
                assert r.headers["Retry-After"]

            server.start()  # same port, same directory: the append-only file brings the data back
            assert c.get("/health").status_code == 200
            assert c.get("/cameras/cell").json()["fx"] == 1000.0
        assert not (tmp_path / "unused").exists()  # with Redis, no cache directory is made
    finally:
        server.stop()


# --- many processes on one Redis (slow: real uvicorn replicas and workers) --------------------------

def _start_worker(redis_url: str, log_path, lease_s: float):
    import os
    import subprocess
    import sys

    from tests.test_server import ROOT

    env = {**os.environ, "POSE_STORE": redis_url, "POSE_BUILD_LEASE_S": str(lease_s)}
    with open(log_path, "ab") as log:  # the process keeps its own copy of the descriptor
        return subprocess.Popen([sys.executable, "-m", "service", "worker"], cwd=ROOT, env=env, stdout=log,
                                stderr=subprocess.STDOUT, start_new_session=True)


def _kill_group(proc) -> None:
    import contextlib
    import os
    import signal

    with contextlib.suppress(ProcessLookupError):
        os.killpg(proc.pid, signal.SIGKILL)
    proc.wait(timeout=30)


@pytest.mark.slow
@needs_redis
def test_two_replicas_two_workers_one_redis(tmp_path, sprayer_bytes, frame, paper_gt):
    """Upload on one replica, estimate on the other; kill -9 the worker building a model: the other
    worker finishes it (after the lease runs out), and it was never built by two at once; restart
    Redis: nothing is lost (append-only file)."""
    import json
    import os
    import signal
    import time
    from pathlib import Path

    from service.stores import open_store
    from tests.test_server import BUILD_WAIT_S, LEASE_S, SLOW_GRID, Server, estimate, upload, wait_status

    redis = RedisServer(tmp_path / "redis").start()
    env = {"POSE_STORE": redis.url}
    replicas, workers = [], []
    try:
        replicas = [Server(tmp_path / "unused", tmp_path / f"api{i}.log", env=env) for i in range(2)]
        workers = [_start_worker(redis.url, tmp_path / f"worker{i}.log", LEASE_S) for i in range(2)]
        a, b = (s.client for s in replicas)

        mid = upload(a, sprayer_bytes, symmetry="y")["id"]
        assert wait_status(b, mid)["status"] == "ready"  # built by a worker, seen by the other replica
        r = estimate(b, mid, frame)
        assert r.status_code == 200 and r.json()["found"] is True
        assert "appearance" not in r.json()["verdict"]["evidence"]
        # a reference photo posted to one replica is taught by the other (its memo is keyed by the record's
        # references_version in Redis): the same share of faces, and the same finding, a plain part
        posted = a.post(f"/models/{mid}/references", files={"image": ("0001.png", frame[0])},
                        data={"camera": json.dumps(frame[1]),
                              "pose": json.dumps({"R": paper_gt["R"], "t_mm": paper_gt["t_mm"]})})
        assert posted.status_code == 201, posted.text
        seen = b.get(f"/models/{mid}/references").json()
        assert seen["references"] == 1 and seen["known_fraction"] == posted.json()["known_fraction"] > 0
        assert seen["plain"] is True and seen["used"] is False
        r = estimate(b, mid, frame)  # a plain part's photos are not used: judged as untaught
        assert r.json()["found"] is True and "appearance" not in r.json()["verdict"]["evidence"]

        slow = upload(a, sprayer_bytes, symmetry="none", templates=json.dumps(SLOW_GRID))["id"]
        deadline = time.monotonic() + BUILD_WAIT_S
        while (info := b.get(f"/models/{slow}").json())["progress"] < 0.1:
            assert info["status"] in ("queued", "building") and time.monotonic() < deadline
            time.sleep(0.05)
        with open_store(redis.url) as store:
            holder_pid = int(store.lock_holder(slow).split(":")[1])  # the worker's work-horse
        parent = int(Path(f"/proc/{holder_pid}/stat").read_text().rsplit(")", 1)[1].split()[1])
        victim = next(w for w in workers if w.pid == parent)  # the worker whose horse builds it
        os.kill(victim.pid, signal.SIGKILL)  # kill -9 the worker mid-build (its horse follows it)
        victim.wait(timeout=30)
        info = wait_status(a, slow)
        assert info["status"] == "ready" and info["progress"] == 1.0 and info["n_templates"] > 0
        with open_store(redis.url) as store:
            assert store.build_count(slow) == 2  # started, killed, finished by the other worker

        redis.restart()  # everything acknowledged before is in the append-only file
        for client in (a, b):
            deadline = time.monotonic() + 30
            while client.get("/health").status_code != 200:
                assert time.monotonic() < deadline
                time.sleep(0.1)
        assert {m["id"]: m["status"] for m in b.get("/models").json()} == {mid: "ready", slow: "ready"}
        assert estimate(a, mid, frame).status_code == 200
        kept = b.get(f"/models/{mid}/references").json()  # the photo survived Redis's restart, and is taught
        assert kept["references"] == 1 and kept["known_fraction"] == posted.json()["known_fraction"]
    finally:
        for w in workers:
            _kill_group(w)
        for s in replicas:
            s.kill()
        redis.stop()


def test_the_scale_compose_file_wires_redis_replicas_workers_and_the_balancer():
    """No Docker engine here: the file is checked statically (as tests/test_docker.py checks compose.yaml)."""
    import re
    from pathlib import Path

    import yaml

    docker = Path(__file__).resolve().parents[1] / "docker"
    compose = yaml.safe_load((docker / "compose.scale.yaml").read_text())
    services = compose["services"]
    redis_cmd = " ".join(services["redis"]["command"])
    assert "--appendonly yes" in redis_cmd and "noeviction" in redis_cmd  # persisted, never evicts a bank
    assert any(v.startswith("redis_data:") for v in services["redis"]["volumes"])
    assert "redis_data" in compose["volumes"]
    for name in ("api", "worker"):
        s = services[name]
        assert s["build"]["dockerfile"] == "docker/Dockerfile"
        assert s["environment"]["POSE_STORE"] == "redis://redis:6379/0"
        assert s["depends_on"]["redis"]["condition"] == "service_healthy" and s["restart"] == "unless-stopped"
        # every setting but the cache dir and the build pool, which a Redis deployment does not use
        unused = {"POSE_CACHE_DIR", "POSE_BUILD_WORKERS"}
        assert set(s["environment"]) == {f"POSE_{f.upper()}" for f in Settings.model_fields} - unused, name
    assert services["worker"]["command"] == ["python", "-m", "service", "worker"]
    assert "/health" in " ".join(services["api"]["healthcheck"]["test"]) and "ports" not in services["api"]
    lb = services["lb"]
    assert lb["ports"] == ["8000:8000"]
    conf_mount = next(v for v in lb["volumes"] if "nginx" in v)
    conf = (docker / conf_mount.split(":")[0].removeprefix("./")).read_text()
    assert re.search(r"set \$api http://api:8000;", conf) and "proxy_pass $api;" in conf
    size_mb = int(re.search(r"client_max_body_size (\d+)m;", conf).group(1))
    assert size_mb * 1024 * 1024 >= Settings().max_mesh_bytes  # the balancer lets a largest mesh through


@needs_redis
def test_the_sweep_requeues_only_a_build_nobody_holds_or_waits_for(redis_url):
    """The retry of a killed worker's build: an unfinished model with no lease and no queued job is
    queued again once it has been so for the grace period, once; a held lease or a waiting job stops it."""
    from rq import Queue

    from service.jobs import queue as jobs
    from service.stores import open_store

    settings = Settings(store=redis_url, build_lease_s=30)
    with open_store(redis_url) as store, jobs._connection(settings) as conn:
        queue = Queue(jobs.QUEUE_NAME, connection=conn)
        store.create({"id": "orphan", "status": "building", "created_at": "1"}, b"mesh")
        store.create({"id": "held", "status": "building", "created_at": "2"}, b"mesh")
        store.create({"id": "done", "status": "ready", "created_at": "3"}, b"mesh")
        assert store.try_lock("held", lease_s=30)

        orphans: dict[str, float] = {}
        assert jobs.sweep(store, queue, settings, orphans, grace_s=3600) == []  # not orphaned long enough
        assert list(orphans) == ["orphan"]
        assert jobs.sweep(store, queue, settings, orphans, grace_s=0) == ["orphan"]
        assert jobs.queued_ids(queue) == {"orphan"}
        assert jobs.sweep(store, queue, settings, orphans, grace_s=0) == []  # its job is waiting

        builder = jobs.QueueBuilder(settings)
        builder.cancel("orphan")  # a deleted model's waiting job goes too
        assert jobs.queued_ids(queue) == set()
        builder.submit("held")
        builder.submit("held")  # one waiting job per model
        assert queue.count == 1
        builder.shutdown()
