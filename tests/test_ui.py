"""The pages for people: the operator page ``/ui`` and the API docs, served with no internet.

Fast tests check that nothing the pages load comes from another host and that every file they name
is served. The slow ones start the service (a real uvicorn on a loopback port) and drive ``/ui`` and
``/docs`` in headless Chromium over the DevTools Protocol (``tests/cdp.py`` says why CDP): pick a
model and a registered camera, upload the image, estimate, and check what the page shows against the
scene's known answer. ``POSE_UI_SCREENSHOT=path`` also saves the page's screenshot there (the one in
``docs/`` is made so).
"""

from __future__ import annotations

import base64
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
from service.vision.overlay import REFINED_BGR
from tests.api_helpers import BUILD_WAIT_S
from tests.test_api_cell import (
    COPIES_DISTANCE_MM,
    GRASPS,
    INTRINSICS,
    T_BASE_CAM,
    T_CAM_OBJ,
    T_CAM_OBJS,
    H,
    K,
    W,
    render_copies,
    render_scene,
    transform,
)
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


def pick_part_and_camera(browser, mid: str, camera: str = "cell-cam", distance_mm: float = 450.0) -> None:
    """The page's part set to ``mid``, its camera to ``camera``, the distance to ``distance_mm``."""
    browser.wait_for(f"[...document.querySelectorAll('#model option')].some(o => o.value === '{mid}') && "
                     f"[...document.querySelectorAll('#camera option')].some(o => o.value === '{camera}')")
    browser.js(f"(() => {{ const s = document.getElementById('model'); s.value = '{mid}'; "
               "s.dispatchEvent(new Event('change')); const c = document.getElementById('camera'); "
               f"c.value = '{camera}'; c.dispatchEvent(new Event('change')); "
               f"document.getElementById('distance').value = '{distance_mm:g}'; }})()")


def record_requests(browser) -> None:
    """From now on the page keeps every estimate's options as sent in ``window.sentOptions``."""
    browser.js("(() => { window.sentOptions = []; const send = window.fetch; "
               "window.fetch = (path, init) => { "
               "if (init && init.body instanceof FormData && init.body.has('options')) "
               "window.sentOptions.push(JSON.parse(init.body.get('options'))); "
               "return send(path, init); }; })()")


def sent_options(browser) -> dict:
    return browser.js("window.sentOptions[window.sentOptions.length - 1]")


def decoded(data_url: str) -> np.ndarray:
    """A ``data:image/png;base64,...`` URL -> (H, W, 3) uint8 BGR."""
    data = base64.b64decode(data_url.split(",", 1)[1])
    return cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)


def overlay_image(browser) -> np.ndarray:
    """The overlay of the page's result, decoded (BGR)."""
    return decoded(browser.wait_for("document.getElementById('overlay').getAttribute('src')"))


def shown_overlay(browser) -> bool:
    return browser.js("(() => { const o = document.getElementById('overlay'); "
                      "return !!o.getAttribute('src') || getComputedStyle(o).display !== 'none'; })()")


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
def test_an_error_after_a_found_result_clears_it_and_shows_the_services_sentence(browser, served, scene,
                                                                                  tmp_path):
    server, mid = served
    image = tmp_path / "scene.png"
    image.write_bytes(scene)
    browser.goto(f"{server.url}/ui")
    pick_part_and_camera(browser, mid)
    browser.set_files("#image", image)
    browser.click("#estimate")
    assert text_once(browser, "verdict", "^FOUND").startswith("FOUND")
    assert shown_overlay(browser) and browser.js("document.querySelectorAll('#pose tr').length") > 0
    wrong = json.dumps({**INTRINSICS, "width": 1280, "height": 960})
    browser.js("(() => { const c = document.getElementById('camera'); c.value = ''; "
               "c.dispatchEvent(new Event('change')); "
               f"document.getElementById('intrinsics').value = {json.dumps(wrong)}; }})()")
    browser.click("#estimate")
    error = browser.wait_for("document.getElementById('error').textContent")
    assert error.startswith("The image is 640x480 pixels but the camera part's width and height say 1280x960")
    assert browser.js("document.getElementById('verdict').textContent") == "no result"
    assert not shown_overlay(browser)
    picture = decoded(browser.js("document.getElementById('roi-canvas').toDataURL('image/png')"))
    assert picture.shape == (H, W, 3)  # the image as chosen, without the earlier result's contour
    assert not np.all(picture == np.array(REFINED_BGR, np.uint8), axis=2).any()
    for box in ("pose", "grasps", "instances"):
        assert browser.js(f"document.getElementById('{box}').textContent") == "", box
    assert "FOUND" not in browser.js("document.querySelector('main').innerText")


@pytest.mark.slow
def test_part_list_tells_two_uploads_of_one_file_apart(browser, served, lbracket, tmp_path):
    """The fixture's lbracket.stl (mm) uploaded again from the page in cm: two entries of one name,
    each saying its units and size."""
    server, mid = served
    mesh = tmp_path / "lbracket.stl"
    mesh.write_bytes(lbracket[0])
    browser.goto(f"{server.url}/ui")
    browser.wait_for(f"[...document.querySelectorAll('#model option')].some(o => o.value === '{mid}')")
    browser.js("document.querySelector('details').open = true; document.getElementById('units').value = 'cm'")
    browser.set_files("#mesh", mesh)
    browser.click("#upload")
    other = browser.wait_for("(() => { const o = [...document.querySelectorAll('#model option')]"
                             f".find(o => o.value !== '{mid}'); return o ? o.value : ''; }})()")
    try:
        texts = browser.js("Object.fromEntries([...document.querySelectorAll('#model option')]"
                           ".map(o => [o.value, o.textContent]))")
        assert texts[mid].startswith("lbracket.stl - mm, 100 x 80 x 60 mm ("), texts
        assert texts[other].startswith("lbracket.stl - cm, 1000 x 800 x 600 mm ("), texts
    finally:
        server.client.delete(f"/models/{other}")


def drag(browser, selector: str, from_uv, to_uv, image_size) -> None:
    """A mouse drag on ``selector`` (showing an image of ``image_size`` = (w, h) scaled to fit) from
    image pixel ``from_uv`` to ``to_uv``."""
    left, top, width, height = browser.js(
        f"(() => {{ const r = document.querySelector({json.dumps(selector)}).getBoundingClientRect(); "
        "return [r.left, r.top, r.width, r.height]; })()")

    def client_xy(uv):
        return left + uv[0] * width / image_size[0], top + uv[1] * height / image_size[1]

    half_way = ((from_uv[0] + to_uv[0]) / 2, (from_uv[1] + to_uv[1]) / 2)
    steps = [("mousePressed", from_uv), ("mouseMoved", half_way), ("mouseMoved", to_uv),
             ("mouseReleased", to_uv)]
    for kind, uv in steps:
        x, y = client_xy(uv)
        browser.send("Input.dispatchMouseEvent", type=kind, x=x, y=y, button="left", buttons=1, clickCount=1)


def copy_borders(lbracket) -> list[np.ndarray]:
    """Each copy's silhouette border in the two-copy scene: (H, W) bool."""
    from service.vision.geometry.frames import Pose
    from service.vision.geometry.render import render

    mesh, out = lbracket[1], []
    for T in T_CAM_OBJS:
        m = render(mesh.vertices, mesh.faces, Pose.from_matrix(T), K, (W, H)).mask.astype(np.uint8)
        out.append((m - cv2.erode(m, np.ones((3, 3), np.uint8))).astype(bool))
    return out


def drawn_on(overlay: np.ndarray, border: np.ndarray) -> float:
    """The share of ``border``'s pixels with the overlay's solid (refined) line within 2 px."""
    line = np.all(overlay == np.array(REFINED_BGR, np.uint8), axis=2).astype(np.uint8)
    near = cv2.dilate(line, np.ones((5, 5), np.uint8)).astype(bool)
    return float(near[border].mean())


@pytest.mark.slow
def test_every_instance_is_drawn_and_listed_and_a_dragged_region_is_searched(browser, served, lbracket,
                                                                              tmp_path):
    """Two copies: max_instances 2 lists both (each row at its copy's pose, in the base frame too) and
    outlines both on the overlay; a region dragged around the first copy is sent and finds it alone."""
    server, mid = served
    image = tmp_path / "copies.png"
    image.write_bytes(render_copies(lbracket[1]))
    borders = copy_borders(lbracket)
    browser.goto(f"{server.url}/ui")
    record_requests(browser)
    pick_part_and_camera(browser, mid, distance_mm=COPIES_DISTANCE_MM)
    browser.js("document.getElementById('max-instances').value = '2'; "
               "document.getElementById('min-score').value = '0.5'")
    browser.set_files("#image", image)
    browser.click("#estimate")
    assert text_once(browser, "verdict", "^FOUND").startswith("FOUND")
    assert sent_options(browser)["max_instances"] == 2 and sent_options(browser)["min_score"] == 0.5
    rows = browser.js("[...document.querySelectorAll('#instances tr')].slice(1).map(r => r.innerText)")
    assert len(rows) == 2, rows
    listed = []
    for row in rows:
        values = numbers(row)  # score, t_mm (3), euler (3), base t_mm (3), grasp angle
        copy = int(np.argmin([np.linalg.norm(np.subtract(values[1:4], T[:3, 3])) for T in T_CAM_OBJS]))
        np.testing.assert_allclose(values[1:4], T_CAM_OBJS[copy][:3, 3], atol=CELL_GRASP_T_MM)
        np.testing.assert_allclose(values[7:10], (T_BASE_CAM @ T_CAM_OBJS[copy])[:3, 3], atol=CELL_GRASP_T_MM)
        listed.append(copy)
    assert sorted(listed) == [0, 1]
    overlay = overlay_image(browser)
    assert overlay.shape == (H, W, 3)
    assert drawn_on(overlay, borders[0]) > 0.8 and drawn_on(overlay, borders[1]) > 0.8

    # around the first copy only (its silhouette spans about u 63..238, v 81..204)
    browser.wait_for("getComputedStyle(document.getElementById('roi-canvas')).display === 'block'")
    drag(browser, "#roi-canvas", (40, 60), (262, 230), (W, H))
    assert text_once(browser, "roi-info", "region").startswith("region x")
    browser.click("#estimate")
    assert text_once(browser, "verdict", "^FOUND").startswith("FOUND")
    roi = sent_options(browser)["roi"]
    # the preview is about half the image's size: a canvas pixel is about 2 image pixels
    np.testing.assert_allclose([roi["x"], roi["y"], roi["x"] + roi["w"], roi["y"] + roi["h"]],
                               [40, 60, 262, 230], atol=3)
    rows = browser.js("[...document.querySelectorAll('#instances tr')].slice(1).map(r => r.innerText)")
    assert len(rows) == 1, rows
    np.testing.assert_allclose(numbers(rows[0])[1:4], T_CAM_OBJS[0][:3, 3], atol=CELL_GRASP_T_MM)
    overlay = overlay_image(browser)
    assert drawn_on(overlay, borders[0]) > 0.8 and drawn_on(overlay, borders[1]) < 0.2


@pytest.mark.slow
def test_the_registered_cameras_plane_is_offered_and_sent(browser, served, scene, tmp_path):
    """A camera whose plane lies 1000 mm away (the part floats at 450 mm): searched on the plane (the
    page's default for a fixed camera, as the service's) nothing rests there; unticked, the page sends
    ``plane: null`` with the distance and the part is found."""
    server, mid = served
    far_plane = {"normal": [0.0, 0.0, -1.0], "d_mm": -1000.0}
    body = {**INTRINSICS, "width": W, "height": H, "T_base_cam": transform(T_BASE_CAM), "plane": far_plane}
    r = server.client.put("/cameras/table-cam", json=body)
    assert r.status_code in (200, 201), r.text
    try:
        image = tmp_path / "scene.png"
        image.write_bytes(scene)
        browser.goto(f"{server.url}/ui")
        record_requests(browser)
        pick_part_and_camera(browser, mid, camera="table-cam")
        assert browser.js("getComputedStyle(document.getElementById('plane-box')).display") == "block"
        assert browser.js("document.getElementById('use-plane').checked") is True
        assert browser.js("document.getElementById('distance').disabled") is True
        browser.set_files("#image", image)
        browser.click("#estimate")
        assert text_once(browser, "verdict", "NOT FOUND").startswith("NOT FOUND")
        sent = sent_options(browser)
        assert sent["plane"] == far_plane and "distance_mm" not in sent
        browser.click("#use-plane")
        assert browser.js("document.getElementById('distance').disabled") is False
        browser.click("#estimate")
        assert text_once(browser, "verdict", "^FOUND").startswith("FOUND")
        sent = sent_options(browser)
        assert sent["plane"] is None and sent["distance_mm"] == 450.0
        pick_part_and_camera(browser, mid)  # cell-cam has no plane: nothing to offer
        assert browser.js("getComputedStyle(document.getElementById('plane-box')).display") == "none"
    finally:
        server.client.delete("/cameras/table-cam")


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
