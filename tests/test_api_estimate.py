"""The estimate response contract (API.md): fields, types, units, status codes, on a real render.

paper/images/0001.png with its K from paper/gt.jsonl and ``options={"distance_mm": 500}``.
Accuracy is the pipeline's tests' business; here the numbers only have to be in the API's units.
"""

from __future__ import annotations

import base64
import json
import warnings

import cv2
import numpy as np
import pytest

from service.main import create_app
from service.settings import Settings
from service.vision.geometry.frames import R_from_euler_xyz_deg, R_from_quat_xyzw
from tests.api_helpers import wait_built
from tests.tolerances import API_HELD_DISTANCE_MM, API_UNITS_CHECK_MM, ROUND_TRIP_ATOL

with warnings.catch_warnings():  # starlette would like httpx2; the test extra installs httpx
    warnings.filterwarnings("ignore", message="Using `httpx` with `starlette.testclient`")
    from fastapi.testclient import TestClient

GRID = {"tilt_step_deg": 15, "view_step_deg": 45}
POSE_FIELDS = {"R", "t_mm", "euler_xyz_deg", "quaternion_xyzw"}


@pytest.fixture(scope="module")
def camera(frame) -> dict:
    return frame[1]


@pytest.fixture(scope="module")
def image_bytes(frame) -> bytes:
    return frame[0]


@pytest.fixture(scope="module")
def client(tmp_path_factory, sprayer_bytes):
    settings = Settings(cache_dir=tmp_path_factory.mktemp("estimate-cache"), template_grid=GRID)
    with TestClient(create_app(settings)) as c:
        r = c.post("/models", files={"file": ("sprayer.stl", sprayer_bytes)})
        mid = r.json()["id"]
        assert wait_built(c, mid)["status"] == "ready"
        c.model_id = mid
        yield c


def estimate(client, image: bytes, camera: dict, options: dict | None = None):
    data = {"camera": json.dumps(camera)}
    if options is not None:
        data["options"] = json.dumps(options)
    r = client.post(f"/models/{client.model_id}/estimate", files={"image": ("image", image)}, data=data)
    assert r.status_code == 200, r.text
    return r.json()


def check_pose(p: dict) -> None:
    assert set(p) >= POSE_FIELDS
    R = np.asarray(p["R"], float)
    assert R.shape == (3, 3) and len(p["t_mm"]) == 3 and len(p["euler_xyz_deg"]) == 3
    assert len(p["quaternion_xyzw"]) == 4
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-9)
    assert np.linalg.det(R) == pytest.approx(1.0)
    # R = Rx(rx) @ Ry(ry) @ Rz(rz); quaternion in (x, y, z, w) order
    np.testing.assert_allclose(R_from_euler_xyz_deg(p["euler_xyz_deg"]), R, atol=ROUND_TRIP_ATOL)
    np.testing.assert_allclose(R_from_quat_xyzw(p["quaternion_xyzw"]), R, atol=ROUND_TRIP_ATOL)
    assert np.linalg.norm(p["quaternion_xyzw"]) == pytest.approx(1.0)


def check_scored(c: dict) -> None:
    check_pose(c)
    assert isinstance(c["cost"], float) and c["cost"] >= 0.0
    assert isinstance(c["score"], float) and 0.0 <= c["score"] <= 1.0


def test_estimate_result_contract(client, image_bytes, camera, paper_gt):
    res = estimate(client, image_bytes, camera, {"distance_mm": 500})
    assert set(res) >= {"model_id", "image_size", "found", "coarse", "refined", "candidates", "timing_ms"}
    assert res["model_id"] == client.model_id
    assert res["image_size"] == [paper_gt["width"], paper_gt["height"]]  # [w, h]
    assert res["found"] is True
    check_scored(res["coarse"])
    check_scored(res["refined"])
    assert isinstance(res["refined"]["iterations"], int) and res["refined"]["iterations"] >= 0
    assert 0.0 <= res["refined"]["inlier_ratio"] <= 1.0
    assert 1 <= len(res["candidates"]) <= 5  # top_k defaults to 5
    for cand in res["candidates"]:
        check_scored(cand)
    assert set(res["timing_ms"]) == {"edges", "coarse", "refine", "total"}
    assert all(isinstance(v, float) and v >= 0.0 for v in res["timing_ms"].values())
    assert res.get("overlay_png_base64") is None  # overlay defaults to false


def test_translation_is_in_mm_with_the_distance_held(client, image_bytes, camera, paper_gt):
    res = estimate(client, image_bytes, camera, {"distance_mm": 500})
    for pose in (res["coarse"], res["refined"]):
        assert abs(pose["t_mm"][2] - 500.0) <= API_HELD_DISTANCE_MM
        np.testing.assert_allclose(pose["t_mm"][:2], paper_gt["t_mm"][:2], atol=API_UNITS_CHECK_MM)


def test_options_refine_top_k_overlay(client, image_bytes, camera, paper_gt):
    options = {"distance_mm": 500, "refine": False, "top_k": 2, "overlay": True}
    res = estimate(client, image_bytes, camera, options)
    assert res["found"] is True and res["refined"] is None
    assert 1 <= len(res["candidates"]) <= 2
    png = base64.b64decode(res["overlay_png_base64"])
    overlay = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR)
    assert overlay.shape[:2] == (paper_gt["height"], paper_gt["width"])


def test_distance_range_and_distortion_and_colour_jpeg(client, image_bytes, camera):
    colour = cv2.imdecode(np.frombuffer(image_bytes, np.uint8), cv2.IMREAD_COLOR)
    ok, jpeg = cv2.imencode(".jpg", colour, [cv2.IMWRITE_JPEG_QUALITY, 95])
    res = estimate(client, jpeg.tobytes(), {**camera, "dist": [0.0, 0.0, 0.0, 0.0, 0.0]},
                   {"distance_range_mm": [400, 600], "refine": False, "top_k": 1})
    assert res["found"] is True
    assert 400.0 - API_UNITS_CHECK_MM <= res["coarse"]["t_mm"][2] <= 600.0 + API_UNITS_CHECK_MM


def test_empty_scene_is_not_found(client, camera):
    ok, png = cv2.imencode(".png", np.full((960, 1280), 128, np.uint8))
    res = estimate(client, png.tobytes(), camera, {"distance_mm": 500})
    assert res["found"] is False and res["refined"] is None
    assert res["image_size"] == [1280, 960]


def test_max_instances_one_answers_as_without_it(client, image_bytes, camera, paper_gt):
    plain = estimate(client, image_bytes, camera, {"distance_mm": 500})
    one = estimate(client, image_bytes, camera, {"distance_mm": 500, "max_instances": 1, "sort": "score"})
    for key in ("found", "coarse", "refined", "candidates", "verdict", "grasps"):
        assert one[key] == plain[key], key
    assert one["found"] and len(one["instances"]) == 1
    inst = one["instances"][0]
    for key in ("refined", "coarse", "verdict"):
        assert inst[key] == one[key], key
    assert abs(inst["refined"]["t_mm"][0] - paper_gt["t_mm"][0]) <= API_UNITS_CHECK_MM
