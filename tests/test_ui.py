"""The pages for people: the operator page ``/ui`` and the API docs, served with no internet.

Fast tests check that nothing the pages load comes from another host and that every file they name
is served. The slow ones start the service (a real uvicorn on a loopback port) and drive ``/ui`` and
``/docs`` in headless Chromium over the DevTools Protocol (``tests/cdp.py`` says why CDP): pick a
model and a registered camera, upload the image, estimate, and check what the page shows against the
scene's known answer. ``POSE_UI_SCREENSHOT=path`` also saves the page's screenshot there (the one in
``docs/`` is made so).
"""

from __future__ import annotations

import json
import os
import re
import shutil
import time
import warnings

import cv2
import numpy as np
import pytest

from service.main import create_app
from service.settings import Settings
from tests.api_helpers import BUILD_WAIT_S
from tests.test_api_cell import GRASPS, INTRINSICS, T_BASE_CAM, T_CAM_OBJ, H, W, render_scene, transform
from tests.tolerances import CELL_GRASP_T_MM

with warnings.catch_warnings():
    warnings.filterwarnings("ignore", message="Using `httpx` with `starlette.testclient`")
    from fastapi.testclient import TestClient

URL_IN_PAGE = re.compile(r"""(?:src|href)\s*=\s*["']([^"']+)["']|url\(\s*["']?([^"')]+)""")


@pytest.fixture(scope="module")
def client(tmp_path_factory):
    with TestClient(create_app(Settings(cache_dir=tmp_path_factory.mktemp("ui-cache")))) as c:
        yield c


@pytest.mark.parametrize("path", ["/ui", "/docs", "/redoc"])
def test_pages_load_nothing_from_another_host(client, path):
    r = client.get(path)
    assert r.status_code == 200 and r.headers["content-type"].startswith("text/html")
    assert "cdn" not in r.text.lower() and "googleapis" not in r.text
    urls = [a or b for a, b in URL_IN_PAGE.findall(r.text)]
    for url in urls:
        assert not re.match(r"^(https?:)?//", url), f"{path} loads {url} from another host"
        if url.startswith("/"):
            assert client.get(url).status_code == 200, url
    if path != "/ui":
        assert any(u.startswith("/static/") and u.endswith(".js") for u in urls)


def test_docs_assets_are_open_with_an_api_key(tmp_path):
    settings = Settings(cache_dir=tmp_path, api_key="secret")
    with TestClient(create_app(settings)) as c:
        for path in ("/ui", "/docs", "/redoc", "/static/swagger-ui/swagger-ui-bundle.js",
                     "/static/redoc/redoc.standalone.js"):
            assert c.get(path).status_code == 200, path
        assert c.get("/cameras").status_code == 401  # the API itself is not


# --- in a real browser --------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def browser():
    from tests.cdp import Browser, chromium_path

    if chromium_path() is None:
        if os.environ.get("CI"):
            pytest.fail("chromium is not installed; .ci/run installs it (apt-get install chromium)")
        pytest.skip("chromium is not installed (apt-get install chromium)")
    b = Browser()
    yield b
    b.close()


@pytest.fixture(scope="module")
def served(tmp_path_factory, lbracket):
    from tests.test_server import Server

    tmp = tmp_path_factory.mktemp("ui-served")
    server = Server(tmp / "cache", tmp / "server.log",
                    env={"POSE_TEMPLATE_GRID": json.dumps({"view_step_deg": 15}), "POSE_WARM_UP": "false"})
    try:
        c = server.client
        mid = c.post("/models", files={"file": ("lbracket.stl", lbracket[0])}).json()["id"]
        deadline = time.monotonic() + BUILD_WAIT_S
        while c.get(f"/models/{mid}").json()["status"] not in ("ready", "failed"):
            assert time.monotonic() < deadline
            time.sleep(0.2)
        assert c.put("/cameras/cell-cam", json={**INTRINSICS, "width": W, "height": H,
                                                "T_base_cam": transform(T_BASE_CAM)}).status_code == 201
        assert c.put(f"/models/{mid}/grasps", json=GRASPS).status_code == 200
        yield server, mid
    finally:
        server.stop()


@pytest.fixture(scope="module")
def scene(lbracket) -> bytes:
    return render_scene(lbracket[1])


def numbers(text: str) -> list[float]:
    return [float(x) for x in re.findall(r"-?\d+\.\d+", text)]


def pick_part_and_camera(browser, mid: str) -> None:
    """The page's part set to ``mid``, its camera to the cell's, the distance to 450 mm."""
    browser.wait_for(f"[...document.querySelectorAll('#model option')].some(o => o.value === '{mid}') && "
                     "[...document.querySelectorAll('#camera option')].some(o => o.value === 'cell-cam')")
    browser.js(f"(() => {{ const s = document.getElementById('model'); s.value = '{mid}'; "
               "s.dispatchEvent(new Event('change')); const c = document.getElementById('camera'); "
               "c.value = 'cell-cam'; c.dispatchEvent(new Event('change')); "
               "document.getElementById('distance').value = '450'; })()")


def text_once(browser, element_id: str, pattern: str, **kw) -> str:
    """The text of ``element_id`` once it matches the JavaScript regular expression ``pattern``."""
    return browser.wait_for(f"(() => {{ const t = document.getElementById('{element_id}').textContent; "
                            f"return /{pattern}/.test(t) ? t : ''; }})()", **kw)


@pytest.mark.slow
def test_operator_page_estimates_and_shows_pose_grasps_and_overlay(browser, served, scene, tmp_path):
    server, mid = served
    image = tmp_path / "scene.png"
    image.write_bytes(scene)
    browser.goto(f"{server.url}/ui")
    pick_part_and_camera(browser, mid)
    browser.set_files("#image", image)
    browser.click("#estimate")
    verdict = text_once(browser, "verdict", "FOUND")
    assert verdict.startswith("FOUND - score 0.9"), verdict
    assert browser.js("document.getElementById('error').textContent") == ""
    # the overlay is the image itself, drawn for a person
    assert browser.wait_for("document.getElementById('overlay').naturalWidth") == W
    assert browser.js("document.getElementById('overlay').naturalHeight") == H
    # the pose in the robot's base frame, as the page prints it, against the known answer
    rows = browser.js("[...document.querySelectorAll('#pose tr')].map(r => r.innerText)")
    base_row = next(r for r in rows if r.startswith("T_base_obj"))
    np.testing.assert_allclose(numbers(base_row)[:3], (T_BASE_CAM @ T_CAM_OBJ)[:3, 3], atol=CELL_GRASP_T_MM)
    grasp_rows = browser.js("[...document.querySelectorAll('#grasps tr')].slice(1).map(r => r.innerText)")
    assert sorted(r.split()[0] for r in grasp_rows) == sorted(g["name"] for g in GRASPS)
    assert all("base" in r for r in grasp_rows)
    for row in grasp_rows:
        g = next(g for g in GRASPS if g["name"] == row.split()[0])
        T_obj_grasp = np.eye(4)
        T_obj_grasp[:3, :3], T_obj_grasp[:3, 3] = g["T_obj_grasp"]["R"], g["T_obj_grasp"]["t_mm"]
        truth = (T_BASE_CAM @ T_CAM_OBJ @ T_obj_grasp)[:3, 3]
        np.testing.assert_allclose(numbers(row)[:3], truth, atol=CELL_GRASP_T_MM)
    browser.screenshot(tmp_path / "ui.png")
    if os.environ.get("POSE_UI_SCREENSHOT"):
        shutil.copyfile(tmp_path / "ui.png", os.environ["POSE_UI_SCREENSHOT"])
    # an empty floor: nothing to find, and the page says why
    empty = tmp_path / "empty.png"
    empty.write_bytes(cv2.imencode(".png", np.full((H, W, 3), 90, np.uint8))[1].tobytes())
    browser.set_files("#image", empty)
    browser.click("#estimate")
    verdict = text_once(browser, "verdict", "NOT FOUND")
    assert verdict.startswith("NOT FOUND - no candidate"), verdict


@pytest.mark.slow
def test_operator_page_shows_the_services_sentence_on_a_mistake(browser, served, scene, tmp_path):
    server, mid = served
    image = tmp_path / "scene.png"
    image.write_bytes(scene)
    browser.goto(f"{server.url}/ui")
    browser.wait_for(f"[...document.querySelectorAll('#model option')].some(o => o.value === '{mid}')")
    wrong = json.dumps({**INTRINSICS, "width": 1280, "height": 960})
    browser.js(f"(() => {{ document.getElementById('model').value = '{mid}'; "
               "const c = document.getElementById('camera'); c.value = ''; "
               "c.dispatchEvent(new Event('change')); "
               f"document.getElementById('intrinsics').value = {json.dumps(wrong)}; }})()")
    browser.set_files("#image", image)
    browser.click("#estimate")
    error = browser.wait_for("document.getElementById('error').textContent")
    assert error.startswith("The image is 640x480 pixels but the camera part's width and height say 1280x960")
    assert browser.js("document.getElementById('verdict').textContent") == "no result"


@pytest.mark.slow
@pytest.mark.parametrize(("path", "rendered"), [
    ("/docs", "document.querySelector('.swagger-ui .info .title')?.textContent"),
    ("/redoc", "document.querySelector('redoc h1')?.textContent"),
])
def test_api_docs_render_without_internet(browser, served, path, rendered):
    server, _ = served
    browser.goto(f"{server.url}{path}")
    assert "posecell" in browser.wait_for(rendered, timeout_s=60)
    assert "/cameras/{name}" in browser.wait_for("document.body.innerText.includes('/cameras/') && "
                                                 "document.body.innerText", timeout_s=60)


@pytest.mark.slow
def test_operator_page_keeps_a_found_pose_as_a_reference_photo_and_follows_its_calibration(
        browser, served, lbracket, tmp_path):
    """Two photos of a painted part were posted without calibrating; the operator estimates a third, keeps
    it as a reference photo, and the page follows the calibration the POST queued to its end. The kept
    pose is the estimate's refined one (the known pose, within the found tolerance); Forget removes all."""
    from service.vision.geometry.frames import Rx, Ry, rotation_angle_deg
    from tests.test_api_references import FOUND_AT_TRUTH_DEG, FOUND_AT_TRUTH_MM, painted_scene

    server, mid = served
    c = server.client

    def turned(rotation: np.ndarray) -> np.ndarray:
        T = T_CAM_OBJ.copy()
        T[:3, :3] = rotation @ T[:3, :3]
        return T

    for T in (T_CAM_OBJ, turned(Rx(20.0))):
        r = c.post(f"/models/{mid}/references", files={"image": ("ref.png", painted_scene(lbracket[1], T))},
                   data={"camera": json.dumps({"name": "cell-cam"}), "pose": json.dumps(transform(T)),
                         "calibrate": "false"})
        assert r.status_code == 201, r.text
    try:
        T_query = turned(Ry(-20.0))
        image = tmp_path / "painted.png"
        image.write_bytes(painted_scene(lbracket[1], T_query))
        browser.goto(f"{server.url}/ui")
        pick_part_and_camera(browser, mid)
        refs = text_once(browser, "refs", "^2 reference photos")
        assert "colours used" in refs and "calibrate=false" in refs, refs
        browser.set_files("#image", image)
        browser.click("#estimate")
        verdict = text_once(browser, "verdict", "FOUND")
        assert verdict.startswith("FOUND"), verdict
        assert browser.js("getComputedStyle(document.getElementById('keep-box')).display") == "block"
        browser.click("#keep")
        refs = text_once(browser, "refs", "calibrated: min score", timeout_s=BUILD_WAIT_S)
        assert refs.startswith("3 reference photos - colours used"), refs
        listed = c.get(f"/models/{mid}/references").json()
        assert listed["calibration_status"] == "calibrated" and f"{listed['min_score']:.3f}" in refs
        kept = listed["views"][2]["T_cam_obj"]
        assert rotation_angle_deg(np.asarray(kept["R"]), T_query[:3, :3]) < FOUND_AT_TRUTH_DEG
        assert np.linalg.norm(np.asarray(kept["t_mm"]) - T_query[:3, 3]) < FOUND_AT_TRUTH_MM
        browser.click("#forget")
        text_once(browser, "refs", "^no reference photos")
        assert c.get(f"/models/{mid}/references").json()["references"] == 0
    finally:  # the module's other tests see the part untaught
        c.delete(f"/models/{mid}/references")
