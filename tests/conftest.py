"""Shared fixtures: the development data in ../shared/data and the project's meshes."""

from __future__ import annotations

import json
import os
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
DATA_DIR = Path(os.environ.get("POSE_DATA_DIR", ROOT.parent / "shared" / "data"))
MODELS_DIR = DATA_DIR / "models"
# In-process apps (TestClient) skip the start-up warm-up: dozens of them would each run the pipeline
# once; the served processes (tests/test_serve.py builds their environment itself) keep it on.
os.environ.setdefault("POSE_WARM_UP", "false")
# a server's parts are calibrated on a plane only where a test asks for it: a minute of CPU a part
os.environ.setdefault("POSE_PLANE_CALIBRATION_SCENES", "0")
# Tests judge answers, not a loaded machine's speed: no default deadline (tests of it set their own).
os.environ.setdefault("POSE_DEADLINE_MS", "0")


@pytest.fixture(scope="session", autouse=True)
def numba_kernels():
    """Every compiled kernel, compiled (or loaded from numba's on-disk cache) once per session before
    the first test: no test's duration includes it, and the servers the tests start load the kernels
    from the cache instead of each compiling them."""
    from service.vision import pipeline

    pipeline.warm_up()


NO_DATA = "development data not found"
# CI sets it: a run where the data's tests skipped did not test what it says it did
REQUIRE_DATA = os.environ.get("POSE_REQUIRE_DATA", "").lower() in ("1", "true", "yes")


@pytest.fixture(scope="session")
def data_dir() -> Path:
    if not DATA_DIR.is_dir():
        pytest.skip(f"{NO_DATA} at {DATA_DIR} (set POSE_DATA_DIR)")
    return DATA_DIR


def _skipped_for_data(terminalreporter) -> int:
    return sum(NO_DATA in str(r.longrepr) for r in terminalreporter.stats.get("skipped", []))


def pytest_terminal_summary(terminalreporter, exitstatus, config):
    """One visible line when tests skipped for want of ../shared/data; with POSE_REQUIRE_DATA the run
    fails."""
    n = _skipped_for_data(terminalreporter)
    if not n:
        return
    terminalreporter.write_line(f"{n} tests skipped: {NO_DATA} at {DATA_DIR} (set POSE_DATA_DIR)",
                                red=REQUIRE_DATA, yellow=not REQUIRE_DATA, bold=True)
    if REQUIRE_DATA:
        terminalreporter.write_line("POSE_REQUIRE_DATA is set: the run fails", red=True, bold=True)


@pytest.hookimpl(trylast=True)
def pytest_sessionfinish(session, exitstatus):
    reporter = session.config.pluginmanager.get_plugin("terminalreporter")
    if REQUIRE_DATA and reporter is not None and _skipped_for_data(reporter):
        session.exitstatus = pytest.ExitCode.TESTS_FAILED


@pytest.fixture(scope="session")
def sprayer_mesh(data_dir):
    import trimesh

    return trimesh.load(data_dir / "models" / "sprayer.stl", force="mesh")


@pytest.fixture(scope="session")
def tless06_mesh(data_dir):
    import trimesh

    return trimesh.load(data_dir / "models" / "tless_06.ply", force="mesh")


@pytest.fixture(scope="session")
def sprayer_bytes(data_dir) -> bytes:
    return (data_dir / "models" / "sprayer.stl").read_bytes()


@pytest.fixture(scope="session")
def paper_gt(data_dir) -> dict:
    """The ground-truth row of paper/images/0001.png (K, R, t_mm, ...)."""
    return json.loads((data_dir / "paper" / "gt.jsonl").read_text().splitlines()[0])


@pytest.fixture(scope="session")
def frame(data_dir, paper_gt) -> tuple[bytes, dict]:
    """paper/images/0001.png as an upload's bytes, and its camera as the API's JSON."""
    K = paper_gt["K"]
    return (data_dir / "paper" / paper_gt["image"]).read_bytes(), {"fx": K[0][0], "fy": K[1][1],
                                                                   "cx": K[0][2], "cy": K[1][2]}


@pytest.fixture(scope="session")
def l_block_bank():
    """The template bank of the L-shaped block (``tests/scenes.py``; arms of unequal length: no symmetry),
    on the coarse grid the instance and plane tests use."""
    from service.vision import pipeline
    from tests.scenes import L_BLOCK_GRID, l_block

    return pipeline.build_templates(l_block(), symmetry="none", grid=L_BLOCK_GRID)


@pytest.fixture(scope="session")
def lbracket(data_dir):
    """models/lbracket.stl (mm, no symmetry): (its bytes, the trimesh)."""
    import trimesh

    path = data_dir / "models" / "lbracket.stl"
    return path.read_bytes(), trimesh.load(path, force="mesh")


@pytest.fixture(scope="session")
def redis_server(tmp_path_factory):
    """One real redis-server for the session (tests/redis_server.py); each test flushes it first."""
    from tests.redis_server import RedisServer, redis_server_binary

    if redis_server_binary() is None:
        pytest.skip("no redis-server installed: apt-get install redis-server (.ci/run installs it)")
    server = RedisServer(tmp_path_factory.mktemp("redis")).start()
    yield server
    server.stop()


@pytest.fixture
def redis_url(redis_server) -> str:
    """The session's Redis, emptied for this test."""
    import redis

    with redis.Redis.from_url(redis_server.url) as r:
        r.flushall()
    return redis_server.url


@pytest.fixture(params=["disk", "redis"])
def location(request, tmp_path) -> str:
    """Where a Store opens: a cache directory, or the URL of a real (emptied) Redis (both, in turn)."""
    if request.param == "redis":
        return request.getfixturevalue("redis_url")
    return str(tmp_path / "cache")
