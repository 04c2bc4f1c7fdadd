"""A pose's R off orthonormal by up to 0.01 (max |R R^T - I|, ``cell.ROTATION_ATOL``), as other systems'
poses are (Linemod-Occluded's ground truth by up to ~0.009): accepted, snapped to the nearest rotation,
and the answer's ``warnings`` say so; beyond it still a 422. Known answer: the paper render's ground-truth
pose with its R's third row scaled (diag(1, 1, s) @ R: max |R R^T - I| = s^2 - 1), whose nearest
rotation (the polar factor) is that very R."""

from __future__ import annotations

import json

import numpy as np
import pytest

from tests.test_api_errors import assert_error
from tests.test_api_references import client, post, untaught  # noqa: F401  (fixtures: one sprayer model)


@pytest.mark.parametrize("s", [1.004, 0.996])  # max |R R^T - I| = 0.008
def test_a_reference_pose_slightly_off_orthonormal_is_snapped_with_a_warning(untaught, frame,  # noqa: F811
                                                                             paper_gt, s):
    api, (image, camera) = untaught, frame
    R = np.diag([1.0, 1.0, s]) @ np.asarray(paper_gt["R"])
    r = post(api, image, camera, {"R": R.tolist(), "t_mm": paper_gt["t_mm"]}, calibrate="false",
             wait="false")
    assert r.status_code == 201, r.text
    (warning,) = r.json()["warnings"]
    assert warning.startswith("pose's R was off orthonormal by 0.008 (max |R R^T - I|, accepted up to 0.01) "
                              "and was snapped to the nearest rotation")
    photos = api.get(f"/models/{api.model_id}/references").json()["views"]
    stored = np.asarray(photos[0]["T_cam_obj"]["R"])
    np.testing.assert_allclose(stored, paper_gt["R"], atol=1e-9)  # scaling an axis: its rotation is R


def test_an_orthonormal_reference_pose_has_no_warning(untaught, frame, paper_gt):  # noqa: F811
    api, (image, camera) = untaught, frame
    r = post(api, image, camera, {"R": paper_gt["R"], "t_mm": paper_gt["t_mm"]}, calibrate="false",
             wait="false")
    assert r.status_code == 201 and r.json()["warnings"] == [], r.text


def test_a_reference_pose_beyond_the_tolerance_is_still_422(untaught, frame, paper_gt):  # noqa: F811
    api, (image, camera) = untaught, frame
    R = np.diag([1.0, 1.0, 1.01]) @ np.asarray(paper_gt["R"])  # max |R R^T - I| = 0.0201
    pose = json.dumps({"R": R.tolist(), "t_mm": paper_gt["t_mm"]})
    detail = assert_error(post(api, image, camera, pose), 422)
    assert "not a rotation matrix" in detail and "by up to 0.0201; allowed 0.01" in detail


def test_a_camera_whose_extrinsics_are_snapped_says_so_when_registered_and_not_after(client, paper_gt):  # noqa: F811
    R = np.diag([1.0, 1.0, 1.004]) @ np.asarray(paper_gt["R"])  # max |R R^T - I| = 0.008
    body = {"fx": 600.0, "fy": 600.0, "cx": 319.5, "cy": 239.5, "width": 640, "height": 480,
            "T_base_cam": {"R": R.tolist(), "t_mm": [0.0, 0.0, 900.0]}}
    r = client.put("/cameras/snapped-cam", json=body)
    assert r.status_code == 201, r.text
    (warning,) = r.json()["warnings"]
    assert warning.startswith("camera's T_base_cam's R was off orthonormal by 0.008")
    np.testing.assert_allclose(r.json()["T_base_cam"]["R"], paper_gt["R"], atol=1e-9)  # stored snapped
    assert client.get("/cameras/snapped-cam").json()["warnings"] == []
    body["T_base_cam"]["R"] = paper_gt["R"]
    assert client.put("/cameras/snapped-cam", json=body).json()["warnings"] == []  # orthonormal: silent
