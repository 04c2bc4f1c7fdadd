"""When the evidence points at the request rather than the scene, the answer says so (issue 45): a
paper render posted with a focal length 10 times too large, or a distance 10 times too far, is not
found at the requested distance, and the answer's warning names distance_mm and fx / fy."""

from __future__ import annotations

import json
import warnings

import pytest

from service.decode import decode_image
from service.main import create_app
from service.settings import Settings
from service.vision import pipeline
from service.vision.geometry.camera import Intrinsics
from tests.api_helpers import wait_built

with warnings.catch_warnings():  # starlette would like httpx2; the test extra installs httpx
    warnings.filterwarnings("ignore", message="Using `httpx` with `starlette.testclient`")
    from fastapi.testclient import TestClient

GRID = {"tilt_step_deg": 15, "view_step_deg": 45}


@pytest.fixture(scope="module")
def sprayer_bank(sprayer_mesh):
    return pipeline.build_templates(sprayer_mesh, symmetry="auto", grid=GRID)


def paper_intrinsics(paper_gt, scale: float = 1.0) -> Intrinsics:
    K = paper_gt["K"]
    return Intrinsics(K[0][0] * scale, K[1][1] * scale, K[0][2], K[1][2])


def test_a_focal_length_ten_times_too_large_gets_a_sentence_naming_it(sprayer_bank, frame, paper_gt):
    image = decode_image(frame[0], max_pixels=10**8)
    right = pipeline.estimate_image(sprayer_bank, image, paper_intrinsics(paper_gt), distance_mm=500.0)
    assert right.found and right.warnings == ()
    off = pipeline.estimate_image(sprayer_bank, image, paper_intrinsics(paper_gt, 10.0), distance_mm=500.0)
    assert not off.found and len(off.warnings) == 1
    # the part is found where a focal length 10 times too large puts it: 10 times as far (within 10 %)
    assert "fx and fy" in off.warnings[0] and "distance_mm 500 mm" in off.warnings[0]
    far = float(off.warnings[0].split(" but is found ")[1].split(" mm")[0])
    assert far == pytest.approx(10.0 * paper_gt["t_mm"][2], rel=0.1)


def test_a_distance_ten_times_too_far_gets_the_sentence_through_the_api(tmp_path, sprayer_bytes, frame):
    image_bytes, camera = frame
    with TestClient(create_app(Settings(cache_dir=tmp_path, template_grid=GRID))) as c:
        mid = c.post("/models", files={"file": ("sprayer.stl", sprayer_bytes)},
                     data={"symmetry": "y"}).json()["id"]
        assert wait_built(c, mid)["status"] == "ready"

        def post(distance_mm: float) -> dict:
            r = c.post(f"/models/{mid}/estimate", files={"image": ("0001.png", image_bytes)},
                       data={"camera": json.dumps(camera),
                             "options": json.dumps({"distance_mm": distance_mm})})
            assert r.status_code == 200, r.text
            return r.json()

        right, off = post(500.0), post(5000.0)
    assert right["found"] and right["warnings"] == []
    assert not off["found"] and any("options.distance_mm 5000 mm" in w and "times as far" in w
                                    for w in off["warnings"]), off["warnings"]


def test_a_frame_without_the_part_gets_no_sentence(sprayer_bank, data_dir):
    """The probe must not blame the request for an empty scene: absent/0001 (the sprayer not in it) at a
    plausible distance is not found, and nothing is said about the distance or the focal length."""
    import cv2
    import numpy as np

    row = json.loads((data_dir / "absent" / "gt.jsonl").read_text().splitlines()[0])
    image = cv2.imread(str(data_dir / "absent" / row["image"]))
    intr = Intrinsics.from_K(np.array(row["K"]))
    out = pipeline.estimate_image(sprayer_bank, image, intr, distance_mm=550.0)
    assert not out.found and out.warnings == ()
