"""Operations inside one app: the request id (``X-Request-ID``) on every answer, JSON log lines,
``/metrics`` per route and status, the optional API key, and settings read from ``POSE_*``."""

from __future__ import annotations

import io
import json
import logging
import re
import warnings

import pytest
from prometheus_client.parser import text_string_to_metric_families
from pydantic import ValidationError

from service.logs import JsonFormatter
from service.main import create_app
from service.settings import Settings

with warnings.catch_warnings():  # starlette would like httpx2; the test extra installs httpx
    warnings.filterwarnings("ignore", message="Using `httpx` with `starlette.testclient`")
    from fastapi.testclient import TestClient

GENERATED_ID = re.compile(r"[0-9a-f]{32}")
KEY = "k3y-for-tests"


@pytest.fixture
def settings(tmp_path) -> Settings:
    return Settings(cache_dir=tmp_path / "cache", max_mesh_bytes=1000)


@pytest.fixture
def client(settings):
    with TestClient(create_app(settings)) as c:
        yield c


@pytest.fixture
def log_lines():
    """The ``service`` loggers' lines as the JSON formatter writes them, parsed."""
    stream = io.StringIO()
    handler = logging.StreamHandler(stream)
    handler.setFormatter(JsonFormatter())
    logger = logging.getLogger("service")
    old_level = logger.level
    logger.addHandler(handler)
    logger.setLevel(logging.DEBUG)
    yield lambda: [json.loads(line) for line in stream.getvalue().splitlines()]
    logger.removeHandler(handler)
    logger.setLevel(old_level)


def sample(text: str, name: str, **labels: str) -> float:
    for family in text_string_to_metric_families(text):
        for s in family.samples:
            if s.name == name and all(s.labels.get(k) == v for k, v in labels.items()):
                return s.value
    return 0.0


# --- request id -----------------------------------------------------------------------------------

def test_a_usable_request_id_is_echoed_and_a_missing_or_unusable_one_replaced(client):
    assert client.get("/health", headers={"X-Request-ID": "cell-7:frame-0042"}).headers["X-Request-ID"] == \
        "cell-7:frame-0042"
    assert GENERATED_ID.fullmatch(client.get("/health").headers["X-Request-ID"])
    for unusable in ("has a space", "x" * 129, "tab\there"):
        echoed = client.get("/health", headers={"X-Request-ID": unusable}).headers["X-Request-ID"]
        assert GENERATED_ID.fullmatch(echoed), unusable
    ids = {client.get("/health").headers["X-Request-ID"] for _ in range(5)}
    assert len(ids) == 5


@pytest.mark.parametrize("method, path, kwargs, status", [
    ("GET", "/models/0123456789abcdef0123", {}, 404),
    ("GET", "/no/such/route", {}, 404),
    ("DELETE", "/health", {}, 405),
    ("POST", "/models", {"files": {"file": ("a.stl", b"x" * 5000)}}, 413),
    ("POST", "/models", {"files": {"file": ("a.stl", b"not a mesh")}}, 415),
    ("POST", "/models", {"files": {"file": ("a.stl", b"solid x\nendsolid x\n")}, "data": {"units": "km"}},
     422),
])
def test_errors_carry_the_request_id_too(client, method, path, kwargs, status):
    r = client.request(method, path, headers={"X-Request-ID": "err-1"}, **kwargs)
    assert r.status_code == status, r.text
    assert r.headers["X-Request-ID"] == "err-1"
    assert r.json()["detail"].endswith(".")


def test_an_unexpected_exception_is_a_500_sentence_with_its_id_and_a_logged_traceback(settings, log_lines):
    app = create_app(settings)

    def boom() -> None:
        raise RuntimeError("kaput")

    app.add_api_route("/boom", boom)
    with TestClient(app) as c:
        r = c.get("/boom", headers={"X-Request-ID": "boom-1"})
    assert r.status_code == 500 and r.headers["X-Request-ID"] == "boom-1"
    assert r.json()["detail"].startswith("The service failed unexpectedly (RuntimeError)")
    lines = [x for x in log_lines() if x["request_id"] == "boom-1"]
    error = next(x for x in lines if x["level"] == "error")
    assert "RuntimeError: kaput" in error["exc_info"] and error["logger"] == "service"
    access = next(x for x in lines if x["logger"] == "service.access")
    assert access["status"] == 500 and access["path"] == "/boom"


# --- logs -----------------------------------------------------------------------------------------

def test_access_lines_are_json_with_the_request_fields(client, log_lines):
    client.get("/models", headers={"X-Request-ID": "list-1"})
    client.get("/health", headers={"X-Request-ID": "health-1"})
    lines = log_lines()
    access = [x for x in lines if x["logger"] == "service.access"]
    listing = next(x for x in access if x["request_id"] == "list-1")
    assert listing["level"] == "info" and listing["method"] == "GET" and listing["path"] == "/models"
    assert listing["status"] == 200 and listing["duration_ms"] >= 0
    assert set(listing) == {"time", "level", "logger", "message", "request_id", "method", "path", "status",
                            "duration_ms"}
    assert re.fullmatch(r"\d{4}-\d\d-\d\dT\d\d:\d\d:\d\d\.\d{3}\+00:00", listing["time"])
    polled = next(x for x in access if x["request_id"] == "health-1")
    assert polled["level"] == "debug"  # health checks every few seconds are not info


def test_a_log_line_outside_a_request_has_a_null_request_id(log_lines):
    logging.getLogger("service").warning("line with %s", "args")
    (line,) = log_lines()
    assert line["message"] == "line with args" and line["request_id"] is None and line["level"] == "warning"


# --- metrics --------------------------------------------------------------------------------------

def test_metrics_count_requests_per_route_template_and_status(client):
    route = "/models/{model_id}"
    before = client.get("/metrics").text
    for mid in ("aaaa", "bbbb", "cccc"):  # three ids, one route template
        assert client.get(f"/models/{mid}").status_code == 404
    r = client.get("/metrics")
    assert r.status_code == 200 and r.headers["content-type"].startswith("text/plain")
    after = r.text
    name = "posecell_http_requests_total"
    assert sample(after, name, method="GET", route=route, status="404") - \
        sample(before, name, method="GET", route=route, status="404") == 3
    hist = "posecell_http_request_duration_seconds_count"
    assert sample(after, hist, method="GET", route=route, status="404") - \
        sample(before, hist, method="GET", route=route, status="404") == 3
    assert "/models/aaaa" not in after  # raw paths would be a series per model id
    for status in ("queued", "building", "ready", "failed"):
        assert sample(after, "posecell_builds", status=status) == 0
    assert sample(after, "posecell_cache_bytes") > 0


# --- API key --------------------------------------------------------------------------------------

def test_without_an_api_key_setting_no_header_is_needed(client):
    assert client.get("/models").status_code == 200


def test_with_an_api_key_every_route_but_health_and_metrics_needs_it(settings):
    settings = settings.model_copy(update={"api_key": Settings(api_key=KEY).api_key})
    with TestClient(create_app(settings)) as c:
        assert c.get("/health").status_code == 200
        assert c.get("/metrics").status_code == 200
        missing = c.get("/models", headers={"X-Request-ID": "nokey-1"})
        assert missing.status_code == 401 and missing.headers["X-Request-ID"] == "nokey-1"
        assert missing.json() == {"detail": "This service requires an API key; send it in the X-API-Key "
                                            "header."}
        wrong = c.get("/models", headers={"X-API-Key": KEY + "x"})
        assert wrong.status_code == 401 and "not valid" in wrong.json()["detail"]
        assert wrong.json()["detail"].endswith(".") and KEY not in wrong.text
        assert c.get("/models", headers={"X-API-Key": KEY}).status_code == 200
        assert c.get("/models/0123", headers={"X-API-Key": KEY}).status_code == 404
        # refused before the body is read: an unauthenticated upload over the size limit is a 401, not a 413
        big = c.post("/models", files={"file": ("a.stl", b"x" * 5000)})
        assert big.status_code == 401
        big = c.post("/models", files={"file": ("a.stl", b"x" * 5000)}, headers={"X-API-Key": KEY})
        assert big.status_code == 413


def test_the_openapi_schema_documents_the_api_key_on_the_protected_routes():
    schema = create_app().openapi()
    assert schema["components"]["securitySchemes"]["APIKey"] == {
        "type": "apiKey", "in": "header", "name": "X-API-Key",
        "description": schema["components"]["securitySchemes"]["APIKey"]["description"]}
    for path, operations in schema["paths"].items():
        for method, op in operations.items():
            protected = path not in ("/health", "/metrics")
            assert (op.get("security") == [{"APIKey": []}]) == protected, (method, path)
            assert ("401" in op["responses"]) == protected, (method, path)


# --- settings -------------------------------------------------------------------------------------

def test_settings_come_from_pose_variables_and_empty_means_default(monkeypatch):
    monkeypatch.setenv("POSE_WORKERS", "3")
    monkeypatch.setenv("POSE_LOG_LEVEL", "DEBUG")
    monkeypatch.setenv("POSE_API_KEY", "")
    monkeypatch.setenv("POSE_TEMPLATE_GRID", "")
    monkeypatch.setenv("POSE_MAX_IMAGE_BYTES", "")
    s = Settings()
    assert s.workers == 3 and s.log_level == "debug" and s.api_key is None and s.template_grid == {}
    assert s.max_image_bytes == Settings.model_fields["max_image_bytes"].default
    monkeypatch.setenv("POSE_API_KEY", "secret")
    assert Settings().api_key.get_secret_value() == "secret" and "secret" not in repr(Settings())
    monkeypatch.setenv("POSE_LOG_LEVEL", "loud")
    with pytest.raises(ValidationError, match="log_level must be one of"):
        Settings()
