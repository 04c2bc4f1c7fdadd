"""service.references without HTTP: the taught-appearance memo (taught once per set of reference
photos and process, renewed when any process changes the set), the pose checks. Both store backends
(a real Redis, as tests/test_store.py)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from service import references
from service.stores import open_store
from service.vision import pipeline
from service.vision.geometry.camera import Intrinsics
from service.vision.geometry.frames import Pose
from service.vision.model.appearance import Appearance

INTR = Intrinsics(500.0, 500.0, 159.5, 119.5)
SIZE = (320, 240)


@pytest.fixture
def teach_calls(monkeypatch) -> list:
    """Every call of ``pipeline.teach_appearance``: the views it was given (it teaches a fixed colour)."""
    calls: list = []

    def teach(bank, views):
        calls.append(views)
        return Appearance(np.full((len(bank.faces), 3), 100.0, np.float32), len(views))

    monkeypatch.setattr(pipeline, "teach_appearance", teach)
    references._TAUGHT.clear()
    yield calls
    references._TAUGHT.clear()


def _photo() -> bytes:
    ok, png = cv2.imencode(".png", np.full((SIZE[1], SIZE[0], 3), 90, np.uint8))
    assert ok
    return png.tobytes()


def _reference(z_mm: float) -> dict:
    return {"image": _photo(), "camera": {"fx": INTR.fx, "fy": INTR.fy, "cx": INTR.cx, "cy": INTR.cy},
            "camera_name": None, "T_cam_obj": {"R": np.eye(3).tolist(), "t_mm": [0.0, 0.0, z_mm]},
            "width": SIZE[0], "height": SIZE[1]}


def test_the_appearance_is_taught_once_per_reference_set_and_renewed_by_any_process(
        location, teach_calls, l_block_bank):
    bank = l_block_bank
    with open_store(location) as api, open_store(location) as other:
        api.create({"id": "m", "name": "part", "status": "ready", "created_at": "2024-01-01"}, b"mesh")
        assert references.appearance_of(api, api.get("m"), bank) is None and teach_calls == []

        first = api.add_reference("m", _reference(400.0), references.MAX_REFERENCES)
        for _ in range(3):  # every estimate of the same set: taught once
            assert references.appearance_of(api, api.get("m"), bank).n_views == 1
        assert len(teach_calls) == 1

        other.add_reference("m", _reference(420.0), references.MAX_REFERENCES)  # another process
        second = api.get("m")
        assert second["references_version"] != first["references_version"]
        for _ in range(3):
            assert references.appearance_of(api, second, bank).n_views == 2
        assert len(teach_calls) == 2
        assert [float(pose.t_mm[2]) for _, _, pose in teach_calls[-1]] == [400.0, 420.0]

        other.clear_references("m")
        assert references.appearance_of(api, api.get("m"), bank) is None
        assert len(teach_calls) == 2  # nothing to teach


class _Box:
    """A 60 x 40 x 30 mm box centred on the model origin (what pose_problem reads of a bank)."""
    vertices_mm = np.array([[x, y, z] for x in (-30, 30) for y in (-20, 20) for z in (-15, 15)], float)


@pytest.mark.parametrize("t_mm, words", [
    ([0.0, 0.0, -40.0], "centre 40 mm behind the camera"),
    ([0.0, 0.0, 0.4], "millimetres (not metres)"),
    ([0.0, 0.0, 30_000.0], "30 m from the camera"),
    ([400.0, 0.0, 400.0], "mostly outside this 320 x 240 image"),
])
def test_pose_problems_say_what_is_wrong(t_mm, words):
    problem = references.pose_problem(_Box, INTR, Pose(np.eye(3), np.array(t_mm)), SIZE)
    assert problem is not None and words in problem


def test_the_in_image_share_is_the_projected_box_s():
    """The box on the optical axis at 400 mm: its projection spans cx +- 500 * 30 / 385 px (the near
    face, z 385 mm), well inside vertically. With the principal point on the image's right edge
    (u 319.5) half of it is inside: 2 px left of that it is accepted (MIN_IN_IMAGE 0.5), 2 px right
    refused."""
    half_px = 500.0 * 30.0 / 385.0
    for du, ok in ((-2.0, True), (+2.0, False)):
        cx = SIZE[0] - 0.5 + du
        share = (SIZE[0] - 0.5 - (cx - half_px)) / (2 * half_px)
        assert (share >= references.MIN_IN_IMAGE) == ok
        intr = Intrinsics(500.0, 500.0, cx, 119.5)
        problem = references.pose_problem(_Box, intr, Pose(np.eye(3), np.array([0.0, 0.0, 400.0])), SIZE)
        assert (problem is None) == ok, (du, problem)
        if not ok:
            assert f"{100 * share:.0f}% of its projected extent inside" in problem


def test_a_calibration_counts_only_for_the_photo_set_it_was_made_on(location, teach_calls, l_block_bank):
    """The record's calibration carries its set's ``references_version``: another process adding a photo
    makes it stale, and the part is judged at the global operating point until that set is calibrated."""
    bank = l_block_bank
    with open_store(location) as api, open_store(location) as other:
        api.create({"id": "m", "name": "part", "status": "ready", "created_at": "2024-01-01"}, b"mesh")
        record = api.add_reference("m", _reference(400.0), references.MAX_REFERENCES)
        api.update("m", calibration={"references_version": record["references_version"], "photos": 1,
                                     "wrong_score": 0.995})
        taught = references.appearance_of(api, api.get("m"), bank)
        assert taught.calibrated_photos == 1 and taught.wrong_score == 0.995
        assert pipeline.operating_point(taught) >= 0.995
        api.update("m", calibration={"references_version": record["references_version"], "photos": 1,
                                     "wrong_score": None})  # calibrated: no wrong pose judged
        assert references.appearance_of(api, api.get("m"), bank).wrong_score == -np.inf

        other.add_reference("m", _reference(420.0), references.MAX_REFERENCES)
        stale = references.appearance_of(api, api.get("m"), bank)
        assert stale.calibrated_photos == 0 and np.isnan(stale.wrong_score)
        assert pipeline.operating_point(stale) is None
