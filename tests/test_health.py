"""``GET /health``'s readiness: "starting" while the warm-up compiles the kernels, "ready" once it is
done (or when there is none); the service answers either way."""

from __future__ import annotations

import threading
import warnings

from service.main import create_app
from service.settings import Settings
from service.vision import pipeline

with warnings.catch_warnings():  # starlette would like httpx2; the test extra installs httpx
    warnings.filterwarnings("ignore", message="Using `httpx` with `starlette.testclient`")
    from fastapi.testclient import TestClient


def test_health_says_starting_until_the_warm_up_ends(tmp_path, monkeypatch):
    release, entered = threading.Event(), threading.Event()

    def slow_warm_up():
        entered.set()
        release.wait(60)
        return pipeline.EstimateOutput((1, 1), True, None, None, [], {})

    monkeypatch.setattr(pipeline, "warm_up", slow_warm_up)
    with TestClient(create_app(Settings(cache_dir=tmp_path, warm_up=True))) as c:
        assert entered.wait(60)
        r = c.get("/health")
        assert r.status_code == 200 and r.json()["ready"] is False and r.json()["state"] == "starting"
        release.set()
        c.app.state.warm.wait(60)
        assert c.get("/health").json() | {"version": None} == {
            "status": "ok", "version": None, "store": "disk", "ready": True, "state": "ready"}


def test_a_failed_warm_up_still_makes_the_service_ready(tmp_path, monkeypatch):
    def broken_warm_up():
        raise RuntimeError("no kernels")

    monkeypatch.setattr(pipeline, "warm_up", broken_warm_up)
    with TestClient(create_app(Settings(cache_dir=tmp_path, warm_up=True))) as c:
        assert c.app.state.warm.wait(60)
        assert c.get("/health").json()["ready"] is True


def test_without_a_warm_up_the_service_is_ready_at_once(tmp_path):
    with TestClient(create_app(Settings(cache_dir=tmp_path, warm_up=False))) as c:
        assert c.get("/health").json()["state"] == "ready"
