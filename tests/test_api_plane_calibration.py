"""A part's plane calibration through the API (API.md, "Parts on a plane"): queued once the part is
ready, run in the background with its progress in ``GET /models/{id}``, kept in the record, read by an
estimate on a plane, and said in that estimate's warnings until it is done.

The part: tests/scenes.py's L-shaped block on its coarse grid, calibrated on 2 rendered scenes (the
service's default is 12). The frame: a third rendered scene of it (``calibration_scenes.scene``), with
its table plane.
"""

from __future__ import annotations

import io
import json
import time
import warnings

import cv2
import numpy as np
import pytest

from service.main import create_app
from service.plane_calibrations import KEY
from service.settings import Settings
from service.stores import open_store
from service.vision.estimate.verdict import AGREEMENT_EVIDENCE
from service.vision.pipeline.calibration_scenes import scene
from service.vision.pipeline.plane_calibration import MARGIN, MIN_WRONG_PER_SCENE
from tests.api_helpers import wait_built
from tests.scenes import L_BLOCK_GRID, l_block

with warnings.catch_warnings():  # starlette would like httpx2; the test extra installs httpx
    warnings.filterwarnings("ignore", message="Using `httpx` with `starlette.testclient`")
    from fastapi.testclient import TestClient

SCENES = 2
CALIBRATION_LIMIT_S = 600.0  # a bound for a hung calibration (2 scenes take about 20 s), not a speed test


def _stl() -> bytes:
    buf = io.BytesIO()
    l_block().export(buf, file_type="stl")
    return buf.getvalue()


def _estimate(client, mid: str, sc) -> dict:
    ok, png = cv2.imencode(".png", sc.bgr)
    assert ok
    camera = {"fx": sc.intr.fx, "fy": sc.intr.fy, "cx": sc.intr.cx, "cy": sc.intr.cy}
    options = {"plane": {"normal": [float(x) for x in sc.plane.normal], "d_mm": sc.plane.d_mm},
               "max_instances": len(sc.poses)}
    r = client.post(f"/models/{mid}/estimate", files={"image": ("f.png", png.tobytes())},
                    data={"camera": json.dumps(camera), "options": json.dumps(options)})
    assert r.status_code == 200, r.text
    return r.json()


@pytest.fixture(scope="module")
def served(tmp_path_factory):
    cache = tmp_path_factory.mktemp("plane-calibration-cache")
    settings = Settings(cache_dir=cache, template_grid=L_BLOCK_GRID, plane_calibration_scenes=SCENES)
    with TestClient(create_app(settings)) as c:
        r = c.post("/models", files={"file": ("l_block.stl", _stl())}, data={"symmetry": "none"})
        assert r.status_code == 202 and r.json()["plane_calibration"] is None  # not ready yet
        assert wait_built(c, r.json()["id"])["status"] == "ready"
        yield c, r.json()["id"], cache


def test_a_ready_part_is_calibrated_in_the_background_and_an_estimate_on_a_plane_reads_it(served,
                                                                                       l_block_bank):
    client, mid, cache = served
    sc = scene(l_block_bank, np.random.default_rng([9, 0]))
    first = _estimate(client, mid, sc)  # also queues the calibration, if GET has not yet
    seen = []
    deadline = time.monotonic() + CALIBRATION_LIMIT_S
    while time.monotonic() < deadline:
        info = client.get(f"/models/{mid}").json()["plane_calibration"]
        seen.append((info["status"], info["progress"]))
        if info["status"] == "calibrated":
            break
        assert info["status"] in ("queued", "running") and 0.0 <= info["progress"] < 1.0, seen
        time.sleep(0.2)
    else:
        raise AssertionError(f"not calibrated within {CALIBRATION_LIMIT_S} s: {seen[-5:]}")
    assert info["progress"] == 1.0 and info["scenes"] == SCENES
    with open_store(str(cache)) as store:
        kept = store.get(mid)[KEY]
    assert kept["status"] == "calibrated" and kept["scenes"] == SCENES
    if kept["wrong_total"] >= MIN_WRONG_PER_SCENE * SCENES:
        assert info["agreement_min"] == pytest.approx(kept["wrong_max"] + MARGIN)
        # a family's wrong poses are some of the part's: its point is never above the part's
        assert all(a is None or a <= info["agreement_min"] + 1e-12 for a in info["agreement_min_by_rest"])
    else:  # too few wrong candidates to say how high a wrong one reads: not calibrated
        assert info["agreement_min"] is None and info["agreement_min_by_rest"] == []
    assert info["agreement_min_by_rest"] == kept["agreement_min_by_rest"]
    # a place point lies under the part's own point, as kept
    assert info["agreement_min_place"] == kept["agreement_min_place"]
    assert info["agreement_min_place"] is None or info["agreement_min_place"] < info["agreement_min"]
    # the floor, a margin under every right candidate's agreement (none with too few of them), as kept
    assert info["agreement_floor"] == kept["agreement_floor"]
    assert info["agreement_along"] == kept["agreement_along"] in AGREEMENT_EVIDENCE
    assert info["agreement_floor"] is None or info["agreement_floor"] <= 1.0 - MARGIN
    # before: the estimate said the part was not calibrated for a plane; after, only a plain one says so
    assert any("plane calibration is" in w for w in first["warnings"]), first["warnings"]
    after = _estimate(client, mid, sc)
    assert not any("plane calibration is" in w for w in after["warnings"]), after["warnings"]
    plain = any("plane calibration found no" in w for w in after["warnings"])
    assert (info["agreement_min"] is None) == plain


def test_without_scenes_no_calibration_is_made_and_get_says_not_requested(tmp_path):
    settings = Settings(cache_dir=tmp_path, template_grid=L_BLOCK_GRID, plane_calibration_scenes=0)
    with TestClient(create_app(settings)) as c:
        r = c.post("/models", files={"file": ("l_block.stl", _stl())}, data={"symmetry": "none"})
        wait_built(c, r.json()["id"])
        info = c.get(f"/models/{r.json()['id']}").json()["plane_calibration"]
        assert info == {"status": "not_requested", "progress": 0.0, "agreement_min": None, "wrong_max": None,
                        "agreement_floor": None, "agreement_along": None, "agreement_min_by_rest": None,
                        "agreement_min_place": None, "scenes": None, "error": None}
