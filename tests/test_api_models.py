"""Models API: upload (202, Location, ModelInfo), build to ready, idempotency, list/get/delete,
template pictures, persistence and resumed builds across app restarts; health."""

from __future__ import annotations

import json
import re
import warnings

import cv2
import numpy as np
import pytest

from service.main import create_app
from service.settings import Settings
from service.stores import open_store
from service.stores.base import model_id
from tests.api_helpers import wait_built
from tests.test_mesh_check import cube_stl

with warnings.catch_warnings():  # starlette would like httpx2; the test extra installs httpx
    warnings.filterwarnings("ignore", message="Using `httpx` with `starlette.testclient`")
    from fastapi.testclient import TestClient

GRID = {"tilt_step_deg": 15, "view_step_deg": 45}
MODEL_FIELDS = {"id", "name", "status", "progress", "error", "n_templates", "units", "extents_mm", "symmetry",
                "created_at"}


@pytest.fixture
def settings(tmp_path) -> Settings:
    return Settings(cache_dir=tmp_path / "cache", template_grid=GRID)


def test_health(settings):
    with TestClient(create_app(settings)) as c:
        r = c.get("/health")
    assert r.status_code == 200
    assert r.json()["status"] == "ok" and isinstance(r.json()["version"], str)


def test_upload_build_list_picture_delete(settings, sprayer_bytes):
    with TestClient(create_app(settings)) as c:
        r = c.post("/models", files={"file": ("sprayer.stl", sprayer_bytes)})
        assert r.status_code == 202, r.text
        info = r.json()
        mid = info["id"]
        assert r.headers["Location"] == f"/models/{mid}"
        assert set(info) >= MODEL_FIELDS
        assert info["name"] == "sprayer.stl" and info["units"] == "mm" and info["error"] is None
        assert info["extents_mm"] == pytest.approx([60.0, 200.0, 60.0])  # known at upload
        if info["status"] != "ready":  # symmetry "auto": known only once the build has looked
            assert info["symmetry"] is None and info["n_templates"] is None

        seen: list[dict] = []
        ready = wait_built(c, mid, seen)
        assert ready["status"] == "ready", ready["error"]
        progress = [s["progress"] for s in seen]
        assert progress == sorted(progress) and all(0.0 <= p <= 1.0 for p in progress)
        assert ready["progress"] == 1.0 and ready["n_templates"] > 0
        assert ready["symmetry"]["type"] == "continuous"
        axis = np.abs(np.asarray(ready["symmetry"]["axis"]))
        np.testing.assert_allclose(axis, [0.0, 1.0, 0.0], atol=1e-3)

        assert [m["id"] for m in c.get("/models").json()] == [mid]
        assert c.get(f"/models/{mid}").json() == ready

        png = c.get(f"/models/{mid}/templates/0.png")
        assert png.status_code == 200 and png.headers["content-type"] == "image/png"
        picture = cv2.imdecode(np.frombuffer(png.content, np.uint8), cv2.IMREAD_UNCHANGED)
        assert picture.ndim == 3 and picture.shape[2] == 3
        last = c.get(f"/models/{mid}/templates/{ready['n_templates'] - 1}.png")
        assert last.status_code == 200

        r = c.delete(f"/models/{mid}")
        assert r.status_code == 204 and r.content == b""
        assert c.get(f"/models/{mid}").status_code == 404
        assert c.get("/models").json() == []
    with open_store(settings.cache_dir) as store:
        assert store.mesh(mid) is None and store.bank(mid) is None


def test_upload_is_idempotent_and_builds_once(settings, sprayer_bytes):
    def upload(c, filename="sprayer.stl", **data):
        return c.post("/models", files={"file": (filename, sprayer_bytes)}, data=data)

    with TestClient(create_app(settings)) as c:
        first = upload(c, name="bottle").json()
        again = upload(c, "renamed.stl", name="other")
        assert again.status_code == 202 and again.json()["id"] == first["id"]
        assert again.json()["name"] == "bottle"  # the first upload's record
        assert wait_built(c, first["id"])["status"] == "ready"
        after = upload(c, name="bottle").json()
        assert after["id"] == first["id"] and after["status"] == "ready"

        other = upload(c, units="cm").json()
        assert other["id"] != first["id"] and other["extents_mm"] == pytest.approx([600.0, 2000.0, 600.0])
        assert c.delete(f"/models/{other['id']}").status_code == 204
    with open_store(settings.cache_dir) as store:
        assert store.build_count(first["id"]) == 1


def test_explicit_symmetry_is_reported_at_upload(settings, sprayer_bytes):
    with TestClient(create_app(settings)) as c:
        info = c.post("/models", files={"file": ("s.stl", sprayer_bytes)}, data={"symmetry": "y"}).json()
        assert info["symmetry"] == {"type": "continuous", "axis": [0.0, 1.0, 0.0]}
        c.delete(f"/models/{info['id']}")


def test_models_persist_and_unfinished_builds_resume_after_restart(settings, sprayer_bytes):
    mid = model_id(sprayer_bytes, units="mm", symmetry="auto", templates=GRID)
    with open_store(settings.cache_dir) as other_process:
        token = other_process.try_lock(mid, lease_s=600)  # the build cannot start in this first run
        with TestClient(create_app(settings)) as c:
            assert c.post("/models", files={"file": ("sprayer.stl", sprayer_bytes)}).json()["id"] == mid
            assert c.get(f"/models/{mid}").json()["status"] == "queued"
        other_process.unlock(mid, token)
    with TestClient(create_app(settings)) as c:  # the restarted service re-queues the build itself
        assert wait_built(c, mid)["status"] == "ready"
    with TestClient(create_app(settings)) as c:  # and knows the ready model after another restart
        info = c.get(f"/models/{mid}").json()
        assert info["status"] == "ready" and info["n_templates"] > 0
        assert c.get(f"/models/{mid}/templates/0.png").status_code == 200


HOLE_FRACTION = 0.3  # the "mesh missing 30 % of its faces"


def _watertight_warnings(warnings: list[str]) -> list[str]:
    return [w for w in warnings if "not watertight" in w]


def test_a_mesh_with_holes_says_so_at_upload_and_in_its_estimates(settings, frame):
    image, camera = frame
    with TestClient(create_app(settings)) as c:
        infos = {}
        for name, holes in (("holed", HOLE_FRACTION), ("closed", 0.0)):
            r = c.post("/models", files={"file": (f"{name}.stl", cube_stl(holes))})
            assert r.status_code == 202, r.text
            infos[name] = r.json()
        holed, closed = infos["holed"], infos["closed"]
        said = _watertight_warnings(holed["warnings"])
        assert len(said) == 1, holed["warnings"]
        open_edges = int(re.search(r"\(([\d,]+) open edges\)", said[0]).group(1).replace(",", ""))
        assert open_edges > 0
        assert "fill the holes" in said[0]  # how to fix it, not only what is wrong
        assert _watertight_warnings(closed["warnings"]) == []  # the twin without holes: nothing said
        for info in (holed, closed):  # the build gets on with it: a warning, not a refusal
            assert wait_built(c, info["id"])["status"] == "ready"
            assert c.get(f"/models/{info['id']}").json()["warnings"] == info["warnings"]

        def estimate_warnings(mid: str) -> list[str]:
            r = c.post(f"/models/{mid}/estimate", files={"image": ("0001.png", image)},
                       data={"camera": json.dumps(camera), "options": json.dumps({"distance_mm": 500})})
            assert r.status_code == 200, r.text
            assert r.json()["found"] is False  # a sprayer render holds no cube
            return r.json()["warnings"]

        assert _watertight_warnings(estimate_warnings(holed["id"])) == said  # the answer names the mesh
        assert _watertight_warnings(estimate_warnings(closed["id"])) == []
