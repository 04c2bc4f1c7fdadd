"""Into the cell, through the API: a camera registered with its hand-eye result, a part with two
grasps, and one estimate that returns the grasp in the robot's base frame (known answer: the scene
is rendered at a known pose with the project's rasteriser). Then one test per integrator mistake.

The scene: the L-bracket (no symmetry) 450 mm in front of a 640 x 480 camera, the camera fixed in
the cell at a known ``T_base_cam`` (eye-to-hand) or on the flange at a known ``T_flange_cam`` with
the robot at a known ``T_base_flange`` (eye-in-hand).
"""

from __future__ import annotations

import json
import warnings

import cv2
import numpy as np
import pytest
import trimesh

from service.cell import rigid
from service.main import create_app
from service.settings import Settings
from service.vision.geometry.frames import Pose, R_from_euler_xyz_deg, rotation_angle_deg
from service.vision.geometry.render import render_shaded
from tests.api_helpers import wait_built
from tests.tolerances import CELL_GRASP_ROT_DEG, CELL_GRASP_T_MM

with warnings.catch_warnings():  # starlette would like httpx2; the test extra installs httpx
    warnings.filterwarnings("ignore", message="Using `httpx` with `starlette.testclient`")
    from fastapi.testclient import TestClient

GRID = {"view_step_deg": 15}  # the L-bracket at this grid: found, refined to ~0.1 mm / 0.03 deg here
W, H = 640, 480
INTRINSICS = {"fx": 900.0, "fy": 900.0, "cx": 319.5, "cy": 239.5}
K = np.array([[900.0, 0.0, 319.5], [0.0, 900.0, 239.5], [0.0, 0.0, 1.0]])
T_CAM_OBJ = rigid(R_from_euler_xyz_deg([120.0, 20.0, 35.0]), [12.0, -8.0, 450.0])  # the truth
DISTANCE_MM = 450.0
# Camera above the table looking down (its z is the base's -z), turned 30 deg about the vertical
# and tilted 10 deg, 900 mm up: a plausible hand-eye result.
T_BASE_CAM = rigid(R_from_euler_xyz_deg([0.0, 0.0, 30.0]) @ R_from_euler_xyz_deg([190.0, 0.0, 0.0]),
                   [620.0, -140.0, 900.0])
# Eye-in-hand: camera 80 mm off the flange, robot somewhere else in the cell.
T_FLANGE_CAM = rigid(R_from_euler_xyz_deg([0.0, 0.0, 90.0]), [0.0, 80.0, 40.0])
T_BASE_FLANGE = rigid(R_from_euler_xyz_deg([180.0, 0.0, -45.0]), [300.0, 250.0, 700.0])
# Two grasps in the model frame (mm): the approach axis is each grasp frame's +z.
GRASPS = [
    {"name": "side", "T_obj_grasp": {"R": R_from_euler_xyz_deg([0.0, 90.0, 0.0]).tolist(),
                                     "t_mm": [0.0, 40.0, 30.0]}},
    {"name": "top", "T_obj_grasp": {"R": R_from_euler_xyz_deg([180.0, 0.0, 0.0]).tolist(),
                                    "t_mm": [50.0, 10.0, 60.0]}},
]


def transform(T: np.ndarray) -> dict:
    return {"R": T[:3, :3].tolist(), "t_mm": T[:3, 3].tolist()}


def matrix(pose: dict) -> np.ndarray:
    return rigid(pose["R"], pose["t_mm"])


def png(img: np.ndarray) -> bytes:
    ok, buf = cv2.imencode(".png", img)
    assert ok
    return buf.tobytes()


def render_scene(mesh: trimesh.Trimesh) -> bytes:
    """PNG bytes of the L-bracket at ``T_CAM_OBJ`` (shaded, on a grey background)."""
    return png(render_shaded(mesh.vertices, mesh.faces, Pose.from_matrix(T_CAM_OBJ), K, (W, H)))


@pytest.fixture(scope="module")
def scene(lbracket) -> bytes:
    return render_scene(lbracket[1])


@pytest.fixture(scope="module")
def client(tmp_path_factory, lbracket):
    settings = Settings(cache_dir=tmp_path_factory.mktemp("cell-cache"), template_grid=GRID)
    with TestClient(create_app(settings)) as c:
        mid = c.post("/models", files={"file": ("lbracket.stl", lbracket[0])}).json()["id"]
        assert wait_built(c, mid)["status"] == "ready"
        c.model_id = mid
        yield c


def estimate(client, image: bytes, camera: dict, options: dict | None = None):
    data = {"camera": json.dumps(camera),
            "options": json.dumps({"distance_mm": DISTANCE_MM, **(options or {})})}
    return client.post(f"/models/{client.model_id}/estimate", files={"image": ("scene.png", image)},
                       data=data)


def assert_pose_near(got: dict, truth: np.ndarray) -> None:
    T = matrix(got)
    assert np.linalg.norm(T[:3, 3] - truth[:3, 3]) <= CELL_GRASP_T_MM
    assert rotation_angle_deg(T[:3, :3], truth[:3, :3]) <= CELL_GRASP_ROT_DEG


def approach_down_deg(T_base_grasp: np.ndarray) -> float:
    """Angle between a grasp's approach (+z of its frame) and straight down in the base frame."""
    return float(np.degrees(np.arccos(np.clip(T_base_grasp[:3, 2] @ [0.0, 0.0, -1.0], -1.0, 1.0))))


def test_registered_camera_and_two_grasps_give_the_grasp_in_the_base_frame(client, scene):
    """The issue's 'done when': camera with its hand-eye result + part with two grasps -> one estimate
    call -> each grasp in the base frame within 1 mm / 0.5 deg of the known answer."""
    r = client.put("/cameras/cell-cam", json={**INTRINSICS, "width": W, "height": H,
                                              "T_base_cam": transform(T_BASE_CAM)})
    assert r.status_code == 201, r.text
    assert r.json()["mounting"] == "eye-to-hand"
    r = client.put(f"/models/{client.model_id}/grasps", json=GRASPS)
    assert r.status_code == 200, r.text

    r = estimate(client, scene, {"name": "cell-cam"})
    assert r.status_code == 200, r.text
    res = r.json()
    assert res["found"] is True and res["camera_name"] == "cell-cam"
    assert_pose_near(res["refined"], T_CAM_OBJ)
    assert_pose_near(res["refined"]["T_base_obj"], T_BASE_CAM @ T_CAM_OBJ)

    truth = {g["name"]: T_BASE_CAM @ T_CAM_OBJ @ matrix(g["T_obj_grasp"]) for g in GRASPS}
    assert {g["name"] for g in res["grasps"]} == set(truth)
    for g in res["grasps"]:
        assert_pose_near(g["T_base_grasp"], truth[g["name"]])
        assert_pose_near(g["T_cam_grasp"], T_CAM_OBJ @ matrix(GRASPS[[x["name"] for x in GRASPS].index(
            g["name"])]["T_obj_grasp"]))
        assert g["spin_deg"] == 0.0  # not a revolved part
        assert g["approach_angle_deg"] == pytest.approx(approach_down_deg(truth[g["name"]]),
                                                        abs=CELL_GRASP_ROT_DEG)
    # most reachable first: the approach closest to straight down in the base frame
    expected_order = sorted(truth, key=lambda n: approach_down_deg(truth[n]))
    assert [g["name"] for g in res["grasps"]] == expected_order


# Two copies side by side, 650 mm away, turned differently (their silhouettes do not touch): each
# instance's grasps must follow its own pose.
COPIES_DISTANCE_MM = 650.0
T_CAM_OBJS = [rigid(R_from_euler_xyz_deg([120.0, 20.0, 35.0]), [-150.0, -50.0, COPIES_DISTANCE_MM]),
              rigid(R_from_euler_xyz_deg([200.0, -30.0, 100.0]), [60.0, -20.0, COPIES_DISTANCE_MM])]


def render_copies(mesh: trimesh.Trimesh) -> bytes:
    """PNG bytes of the L-bracket at each of ``T_CAM_OBJS`` (shaded, on a grey background)."""
    grey = np.full((H, W), 70, np.uint8)
    for T in T_CAM_OBJS:  # the parts are brighter than the floor and do not overlap
        grey = np.maximum(grey, render_shaded(mesh.vertices, mesh.faces, Pose.from_matrix(T), K, (W, H)))
    return png(grey)


def test_every_instance_carries_the_grasps_of_its_own_pose(client, lbracket):
    """Known answer: each found copy's grasps are ``T_BASE_CAM @ T_cam_obj @ T_obj_grasp`` of the copy
    it is, most reachable first for that copy; the top level keeps the first instance's."""
    r = client.put("/cameras/two-parts-cam", json={**INTRINSICS, "width": W, "height": H,
                                                   "T_base_cam": transform(T_BASE_CAM)})
    assert r.status_code in (200, 201), r.text
    assert client.put(f"/models/{client.model_id}/grasps", json=GRASPS).status_code == 200

    r = estimate(client, render_copies(lbracket[1]), {"name": "two-parts-cam"},
                 {"distance_mm": COPIES_DISTANCE_MM, "max_instances": 2})
    assert r.status_code == 200, r.text
    res = r.json()
    assert len(res["instances"]) == 2
    assert res["instances"][0]["grasps"] == res["grasps"]
    T_obj_grasp = {g["name"]: matrix(g["T_obj_grasp"]) for g in GRASPS}
    copies = []
    for inst in res["instances"]:
        t = np.array(inst["refined"]["t_mm"])
        copy = int(np.argmin([np.linalg.norm(t - T[:3, 3]) for T in T_CAM_OBJS]))
        copies.append(copy)
        T_cam_obj = T_CAM_OBJS[copy]
        assert_pose_near(inst["refined"], T_cam_obj)
        truth = {n: T_BASE_CAM @ T_cam_obj @ G for n, G in T_obj_grasp.items()}
        assert [g["name"] for g in inst["grasps"]] == sorted(truth, key=lambda n: approach_down_deg(truth[n]))
        for g in inst["grasps"]:
            assert_pose_near(g["T_base_grasp"], truth[g["name"]])
            assert_pose_near(g["T_cam_grasp"], T_cam_obj @ T_obj_grasp[g["name"]])
    assert sorted(copies) == [0, 1]  # each copy found once, so the second's grasps are not the first's


def test_eye_in_hand_camera_with_the_robot_pose(client, scene):
    r = client.put("/cameras/wrist", json={**INTRINSICS, "width": W, "height": H,
                                           "T_flange_cam": transform(T_FLANGE_CAM)})
    assert r.status_code in (200, 201), r.text
    assert r.json()["mounting"] == "eye-in-hand"
    r = estimate(client, scene, {"name": "wrist"}, {"robot_pose": transform(T_BASE_FLANGE)})
    assert r.status_code == 200, r.text
    res = r.json()
    assert res["found"] is True
    assert_pose_near(res["refined"]["T_base_obj"], T_BASE_FLANGE @ T_FLANGE_CAM @ T_CAM_OBJ)


def test_inline_camera_with_extrinsics_and_without(client, scene):
    res = estimate(client, scene, {**INTRINSICS, "T_base_cam": transform(T_BASE_CAM)}).json()
    assert_pose_near(res["refined"]["T_base_obj"], T_BASE_CAM @ T_CAM_OBJ)
    assert all(c["T_base_obj"] is not None for c in res["candidates"])
    res = estimate(client, scene, INTRINSICS).json()  # intrinsics only: no base frame, grasps in the camera's
    assert res["refined"]["T_base_obj"] is None and res["camera_name"] is None
    for g in res["grasps"]:
        assert g["T_base_grasp"] is None
        assert_pose_near(g["T_cam_grasp"], T_CAM_OBJ @ matrix(next(
            x["T_obj_grasp"] for x in GRASPS if x["name"] == g["name"])))


def test_camera_crud_and_plane(client):
    body = {**INTRINSICS, "width": W, "height": H, "plane": {"normal": [0.0, 0.0, -2.0], "d_mm": -900.0}}
    assert client.put("/cameras/tmp.cam-1", json=body).status_code == 201
    r = client.put("/cameras/tmp.cam-1", json=body)
    assert r.status_code == 200  # replaced
    got = client.get("/cameras/tmp.cam-1").json()
    assert got["plane"] == {"normal": [0.0, 0.0, -1.0], "d_mm": -450.0}  # unit normal, same plane
    assert got["mounting"] == "none" and got["width"] == W
    assert "tmp.cam-1" in [c["name"] for c in client.get("/cameras").json()]
    assert client.delete("/cameras/tmp.cam-1").status_code == 204
    r = client.get("/cameras/tmp.cam-1")
    assert r.status_code == 404 and "No camera is registered as 'tmp.cam-1'" in r.json()["detail"]


def post_estimate(client, image: bytes, camera: dict, options: dict):
    """An estimate with exactly these options (``estimate`` above always adds the distance)."""
    data = {"camera": json.dumps(camera), "options": json.dumps(options)}
    return client.post(f"/models/{client.model_id}/estimate", files={"image": ("scene.png", image)},
                       data=data)


def test_a_fixed_cameras_registered_plane_is_the_default_plane(client, scene):
    """Known answer: a plane 1000 mm away (facing the camera) with the part floating at 450 mm: searched
    on that plane, nothing rests on it, so nothing is found; opting out (``"plane": null``) or giving the
    distance (which a plane excludes) searches freely and finds the part at its true pose."""
    far_plane = {"normal": [0.0, 0.0, -1.0], "d_mm": -1000.0}
    r = client.put("/cameras/table-cam", json={**INTRINSICS, "width": W, "height": H,
                                               "T_base_cam": transform(T_BASE_CAM), "plane": far_plane})
    assert r.status_code in (200, 201), r.text
    cam = {"name": "table-cam"}
    r = post_estimate(client, scene, cam, {"sort": "height"})  # 'height' needs a plane: the camera's
    assert r.status_code == 200, r.text
    assert r.json()["found"] is False
    for options in ({"plane": None, "distance_range_mm": [440.0, 460.0]}, {"distance_mm": DISTANCE_MM}):
        res = post_estimate(client, scene, cam, options).json()
        assert res["found"] is True, (options, res["verdict"])
        assert "plane_gap_mm" not in res["verdict"]["evidence"]
        assert_pose_near(res["refined"], T_CAM_OBJ)
    r = post_estimate(client, scene, INTRINSICS, {"sort": "height"})  # inline camera: no plane to sort by
    assert r.status_code == 422 and "send options.plane" in r.json()["detail"]


def test_an_eye_in_hand_cameras_plane_is_not_a_default(client, scene):
    """The flange moves the camera over the surface, so a plane registered in its frame is not used."""
    far_plane = {"normal": [0.0, 0.0, -1.0], "d_mm": -1000.0}
    r = client.put("/cameras/wrist-plane", json={**INTRINSICS, "width": W, "height": H,
                                                 "T_flange_cam": transform(T_FLANGE_CAM), "plane": far_plane})
    assert r.status_code in (200, 201), r.text
    res = post_estimate(client, scene, {"name": "wrist-plane"},
                        {"distance_range_mm": [440.0, 460.0], "robot_pose": transform(T_BASE_FLANGE)}).json()
    assert res["found"] is True and "plane_gap_mm" not in res["verdict"]["evidence"]
    assert_pose_near(res["refined"], T_CAM_OBJ)


def test_grasps_round_trip_and_duplicate_names(client):
    got = client.get(f"/models/{client.model_id}/grasps").json()
    assert [g["name"] for g in got] == [g["name"] for g in GRASPS]
    assert got[0]["approach_axis"] == [0.0, 0.0, 1.0]
    r = client.put(f"/models/{client.model_id}/grasps", json=[GRASPS[0], GRASPS[0]])
    assert r.status_code == 422
    assert r.json()["detail"] == "Two grasps are named 'side'; give every grasp of a model its own name."
    r = client.put("/models/0123456789abcdef0123/grasps", json=GRASPS)
    assert r.status_code == 404


# --- the integrator mistakes, one sentence each ---------------------------------------------------------

def test_image_size_differs_from_the_registered_camera(client):
    client.put("/cameras/cell-cam", json={**INTRINSICS, "width": W, "height": H,
                                          "T_base_cam": transform(T_BASE_CAM)})
    r = estimate(client, png(np.full((H // 2, W // 2), 70, np.uint8)), {"name": "cell-cam"})
    assert r.status_code == 422
    assert r.json()["detail"] == (
        "The image is 320x240 pixels but camera 'cell-cam' is registered for 640x480; send the camera's "
        "full, unscaled frames, or register the camera again with the intrinsics of this image size.")


def test_image_size_differs_from_inline_width_and_height(client):
    r = estimate(client, png(np.full((H, W), 70, np.uint8)), {**INTRINSICS, "width": 1280, "height": 960})
    assert r.status_code == 422
    assert r.json()["detail"].startswith("The image is 640x480 pixels but the camera part's width and height "
                                         "say 1280x960")


def test_registered_camera_is_held_to_the_plausibility_bounds(client, scene):
    """The bounds (service/bounds.py) apply to a registered camera too: one registered with its focal
    length in millimetres is refused at the estimate with the likely fix."""
    r = client.put("/cameras/mm-cam", json={**INTRINSICS, "fx": 8.0, "fy": 8.0, "width": W, "height": H})
    assert r.status_code == 201, r.text
    r = estimate(client, scene, {"name": "mm-cam"})
    assert r.status_code == 422
    assert "fx is 8 px, under 50 px" in r.json()["detail"] and "not millimetres" in r.json()["detail"]
    r = estimate(client, scene, INTRINSICS, {"distance_mm": 0.45})  # metres
    assert r.status_code == 422
    assert "did you send metres" in r.json()["detail"]


def test_unknown_camera_name(client, scene):
    r = estimate(client, scene, {"name": "nosuchcam"})
    assert r.status_code == 422
    assert r.json()["detail"] == (
        "No camera is registered as 'nosuchcam'; register it with PUT /cameras/nosuchcam, list the "
        "registered ones with GET /cameras, or send the intrinsics inline.")


def test_camera_name_together_with_intrinsics(client, scene):
    r = estimate(client, scene, {"name": "cell-cam", **INTRINSICS})
    assert r.status_code == 422
    assert r.json()["detail"].startswith(
        "The camera part names a registered camera and also has cx, cy, fx, fy")


def test_eye_in_hand_without_robot_pose(client, scene):
    client.put("/cameras/wrist", json={**INTRINSICS, "width": W, "height": H,
                                       "T_flange_cam": transform(T_FLANGE_CAM)})
    r = estimate(client, scene, {"name": "wrist"})
    assert r.status_code == 422
    assert r.json()["detail"] == (
        "Camera 'wrist' is mounted on the robot's flange (T_flange_cam, eye-in-hand), so every estimate "
        "needs options.robot_pose: send T_base_flange, the flange pose when the image was taken, as "
        "{\"R\": 3x3, \"t_mm\": [x, y, z]}.")


def test_both_extrinsics_given(client):
    r = client.put("/cameras/both", json={**INTRINSICS, "width": W, "height": H,
                                          "T_base_cam": transform(T_BASE_CAM),
                                          "T_flange_cam": transform(T_FLANGE_CAM)})
    assert r.status_code == 422
    assert r.json()["detail"] == (
        "The request JSON body is invalid: give T_base_cam (a camera fixed in the cell, eye-to-hand) or "
        "T_flange_cam (a camera on the robot's flange, eye-in-hand), not both; fix it and send the request "
        "again.")
    assert client.get("/cameras/both").status_code == 404


def test_extrinsics_that_are_not_a_rotation(client):
    bad = {"R": [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, -1.0]], "t_mm": [0.0, 0.0, 0.0]}  # a mirror
    r = client.put("/cameras/mirror", json={**INTRINSICS, "width": W, "height": H, "T_base_cam": bad})
    assert r.status_code == 422
    assert "R is a reflection (determinant -1), not a rotation" in r.json()["detail"]


def test_metres_sized_mesh_gets_a_warning(client, lbracket):
    """The L-bracket's file is in mm (100 x 80 x 60); declared in metres it is a 100 m part."""
    r = client.post("/models", files={"file": ("lbracket.stl", lbracket[0])}, data={"units": "m"})
    assert r.status_code == 202
    info = r.json()
    assert info["extents_mm"] == pytest.approx([100000.0, 80000.0, 60000.0])
    assert len(info["warnings"]) == 1
    assert info["warnings"][0].startswith("extents 100000 x 80000 x 60000 mm: did you mean units=mm?")
    assert client.get(f"/models/{info['id']}").json()["warnings"] == info["warnings"]
    client.delete(f"/models/{info['id']}")
    # the same file in mm: nothing to say
    assert client.get(f"/models/{client.model_id}").json()["warnings"] == []
