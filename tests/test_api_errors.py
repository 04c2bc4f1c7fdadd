"""API.md's error table, one test per row: the status AND a one-sentence ``detail``.

A ready model (the sprayer, small grid) is built once for the module; the rows about upload size
use their own apps with tiny limits.
"""

from __future__ import annotations

import json
import warnings

import cv2
import numpy as np
import pytest

from service.main import create_app
from service.settings import Settings
from service.stores import open_store
from service.stores.base import model_id
from tests.api_helpers import wait_built

with warnings.catch_warnings():  # starlette would like httpx2; the test extra installs httpx
    warnings.filterwarnings("ignore", message="Using `httpx` with `starlette.testclient`")
    from fastapi.testclient import TestClient

GRID = {"tilt_step_deg": 15, "view_step_deg": 45}
CAMERA = {"fx": 1100.0, "fy": 1100.0, "cx": 643.0, "cy": 477.0}


def assert_error(r, status: int) -> str:
    assert r.status_code == status, r.text
    detail = r.json()["detail"]
    assert isinstance(detail, str), detail
    assert detail.endswith(".") and "\n" not in detail and detail[0].isupper(), detail
    return detail


@pytest.fixture(scope="module")
def image_bytes(data_dir) -> bytes:
    return (data_dir / "paper" / "images" / "0001.png").read_bytes()


@pytest.fixture(scope="module")
def client(tmp_path_factory, sprayer_bytes):
    settings = Settings(cache_dir=tmp_path_factory.mktemp("errors-cache"), template_grid=GRID)
    with TestClient(create_app(settings)) as c:
        r = c.post("/models", files={"file": ("sprayer.stl", sprayer_bytes)}, data={"symmetry": "y"})
        assert r.status_code == 202
        assert wait_built(c, r.json()["id"])["status"] == "ready"
        c.ready_id = r.json()["id"]
        yield c


def estimate(client, mid, image=None, camera=CAMERA, options=None, image_bytes=b""):
    files = {"image": ("img.png", image if image is not None else image_bytes)}
    data = {"camera": camera if isinstance(camera, str) else json.dumps(camera)}
    if options is not None:
        data["options"] = options if isinstance(options, str) else json.dumps(options)
    return client.post(f"/models/{mid}/estimate", files=files, data=data)


# --- unknown model id: 404 ------------------------------------------------------------------------

@pytest.mark.parametrize("method, path", [("GET", "/models/{id}"), ("DELETE", "/models/{id}"),
                                          ("GET", "/models/{id}/templates/0.png")])
def test_unknown_model_is_404(client, method, path):
    detail = assert_error(client.request(method, path.format(id="0123456789abcdef0000")), 404)
    assert "0123456789abcdef0000" in detail


def test_unknown_model_estimate_is_404(client, image_bytes):
    assert_error(estimate(client, "nope", image=image_bytes), 404)


def test_template_index_out_of_range_is_404(client):
    assert_error(client.get(f"/models/{client.ready_id}/templates/100000.png"), 404)
    assert_error(client.get(f"/models/{client.ready_id}/templates/-1.png"), 404)


def test_unknown_route_and_method(client):
    assert_error(client.get("/no/such/route"), 404)
    assert_error(client.post("/health"), 405)


# --- model not ready: 409 with Retry-After ----------------------------------------------------------

def test_not_ready_is_409_with_retry_after(tmp_path, sprayer_bytes, image_bytes):
    """Another process holds the model's build lease, so the build here waits: the model stays queued."""
    settings = Settings(cache_dir=tmp_path, template_grid=GRID)
    mid = model_id(sprayer_bytes, units="mm", symmetry="auto", templates=GRID)
    with open_store(tmp_path) as other_process, TestClient(create_app(settings)) as c:
        assert other_process.try_lock(mid, lease_s=600) is not None
        r = c.post("/models", files={"file": ("sprayer.stl", sprayer_bytes)})
        assert r.status_code == 202 and r.json()["id"] == mid
        for resp in (estimate(c, mid, image=image_bytes), c.get(f"/models/{mid}/templates/0.png")):
            detail = assert_error(resp, 409)
            assert int(resp.headers["Retry-After"]) > 0 and "not ready" in detail
        assert c.get(f"/models/{mid}").json()["status"] in ("queued", "building")


# --- build failed: 409, detail says why ---------------------------------------------------------------

def test_build_failed_is_409_with_the_reason(tmp_path, sprayer_bytes, image_bytes):
    # valid options, impossible for this mesh: the reference distance must exceed 1.2 x its diameter
    with TestClient(create_app(Settings(cache_dir=tmp_path, template_grid=GRID))) as c:
        r = c.post("/models", files={"file": ("sprayer.stl", sprayer_bytes)},
                   data={"templates": json.dumps({"reference_distance_mm": 100})})
        assert r.status_code == 202
        info = wait_built(c, r.json()["id"])
        assert info["status"] == "failed" and "reference_distance_mm" in info["error"]
        detail = assert_error(estimate(c, info["id"], image=image_bytes), 409)
        assert "failed" in detail and "reference_distance_mm" in detail
        assert "Retry-After" not in estimate(c, info["id"], image=image_bytes).headers


# --- not a mesh / not an image / empty / truncated: 415 or 422 ------------------------------------------

@pytest.mark.parametrize("filename, content, status", [
    ("part.step", b"ISO-10303-21;", 415),  # a format we do not read
    ("notes.stl", b"this is not a mesh\n" * 10, 415),
    ("empty.stl", b"", 422),
    ("cloud.obj", b"v 0 0 0\nv 1 0 0\nv 0 1 0\n", 422),  # no faces
    ("nan.obj", b"v nan 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n", 422),
])
def test_bad_mesh_upload(client, filename, content, status):
    assert_error(client.post("/models", files={"file": (filename, content)}), status)


def test_truncated_mesh_upload(client, sprayer_bytes):
    r = client.post("/models", files={"file": ("sprayer.stl", sprayer_bytes[: len(sprayer_bytes) // 3])})
    assert r.status_code in (415, 422)
    assert_error(r, r.status_code)


@pytest.mark.parametrize("case", ["garbage", "empty", "truncated"])
def test_bad_image(client, image_bytes, case):
    image = {"garbage": b"definitely not a picture " * 40, "empty": b"",
             "truncated": image_bytes[: len(image_bytes) // 2]}[case]
    r = estimate(client, client.ready_id, image=image)
    assert r.status_code in (415, 422)
    assert_error(r, r.status_code)


# --- over the size limit: 413 --------------------------------------------------------------------------

def test_mesh_over_limit_is_413(tmp_path, sprayer_bytes):
    with TestClient(create_app(Settings(cache_dir=tmp_path, max_mesh_bytes=100_000))) as c:
        # the body is within the request limit (file limit + form overhead): the part check stops it
        assert_error(c.post("/models", files={"file": ("sprayer.stl", sprayer_bytes)}), 413)
        # the body is over the request limit: refused from Content-Length before it is read
        big = sprayer_bytes * 3
        assert_error(c.post("/models", files={"file": ("big.stl", big)}), 413)
        assert c.get("/models").json() == []


def test_body_without_content_length_is_counted_while_reading(tmp_path, sprayer_bytes):
    """A chunked upload (no Content-Length) is stopped by counting the bytes as they arrive."""
    boundary = "pose-boundary"
    head = (f"--{boundary}\r\nContent-Disposition: form-data; name=\"file\"; filename=\"big.stl\"\r\n"
            "Content-Type: application/octet-stream\r\n\r\n").encode()

    def body():
        yield head
        for _ in range(4):
            yield sprayer_bytes
        yield f"\r\n--{boundary}--\r\n".encode()

    with TestClient(create_app(Settings(cache_dir=tmp_path, max_mesh_bytes=100_000))) as c:
        r = c.post("/models", content=body(),
                   headers={"Content-Type": f"multipart/form-data; boundary={boundary}"})
        assert "content-length" not in {k.lower() for k in r.request.headers}
        assert_error(r, 413)
        assert c.get("/models").json() == []


@pytest.fixture
def limits(client):
    """The module app's settings, to lower a limit for one test (restored afterwards)."""
    settings = client.app.state.settings
    saved = settings.model_dump()
    yield settings
    for key, value in saved.items():
        setattr(settings, key, value)


def test_image_over_byte_limit_is_413(client, limits, image_bytes):
    limits.max_image_bytes = len(image_bytes) - 1  # within the request limit: the part check stops it
    assert "bytes" in assert_error(estimate(client, client.ready_id, image=image_bytes), 413)
    limits.max_image_bytes = 1000  # over the request limit: refused before the body is read
    assert_error(estimate(client, client.ready_id, image=image_bytes * 2), 413)


def test_image_over_pixel_limit_is_413(client, limits, image_bytes):
    limits.max_image_pixels = 1280 * 960 - 1
    assert "pixels" in assert_error(estimate(client, client.ready_id, image=image_bytes), 413)


# --- bad JSON, fx <= 0, distance <= 0, NaN anywhere: 422 -------------------------------------------------

@pytest.mark.parametrize("camera, options", [
    ("{not json", None),
    ("[1100, 1100, 643, 477]", None),
    ({**CAMERA, "fx": 0}, None),
    ({**CAMERA, "fy": -5}, None),
    ('{"fx": NaN, "fy": 1100, "cx": 643, "cy": 477}', None),
    ('{"fx": 1100, "fy": 1100, "cx": Infinity, "cy": 477}', None),
    ({**CAMERA, "dist": [0.1, 0.2, 0.3]}, None),
    ({"fx": 1100, "fy": 1100, "cx": 643}, None),
    ({**CAMERA, "k1": 0.1}, None),
    (CAMERA, "{bad json"),
    (CAMERA, {"distance_mm": 0}),
    (CAMERA, {"distance_mm": -500}),
    (CAMERA, '{"distance_mm": NaN}'),
    (CAMERA, {"distance_range_mm": [800, 300]}),
    (CAMERA, {"distance_range_mm": [0, 300]}),
    (CAMERA, {"distance_mm": 500, "distance_range_mm": [300, 800]}),
    (CAMERA, {"top_k": 0}),
    (CAMERA, {"top_k": 51}),
    (CAMERA, {"distance": 500}),
])
def test_bad_camera_or_options_is_422(client, image_bytes, camera, options):
    assert_error(estimate(client, client.ready_id, image=image_bytes, camera=camera, options=options), 422)


def test_missing_part_is_422(client, image_bytes):
    r = client.post(f"/models/{client.ready_id}/estimate", files={"image": ("i.png", image_bytes)})
    assert "camera" in assert_error(r, 422)
    assert "file" in assert_error(client.post("/models", data={"name": "no file"}), 422)


@pytest.mark.parametrize("data", [
    {"units": "furlong"},
    {"symmetry": "w"},
    {"templates": "{not json"},
    {"templates": "[15, 45]"},
    {"templates": '{"tilt_step_deg": NaN}'},
    {"templates": '{"tilt_step_deg": 0}'},
    {"templates": '{"no_such_option": 1}'},
])
def test_bad_upload_fields_are_422(client, sprayer_bytes, data):
    assert_error(client.post("/models", files={"file": ("sprayer.stl", sprayer_bytes)}, data=data), 422)


def test_sixteen_bit_colour_image_is_accepted(client):
    """Not an error row: a 16-bit colour TIFF decodes (the estimate may or may not find the object)."""
    ok, tif = cv2.imencode(".tif", np.zeros((48, 64, 3), np.uint16))
    r = estimate(client, client.ready_id, image=tif.tobytes(), options={"distance_mm": 500},
                 camera={"fx": 100.0, "fy": 100.0, "cx": 31.5, "cy": 23.5})
    assert r.status_code == 200, r.text
    assert r.json()["image_size"] == [64, 48]


# --- issue "Reliability": no 500 on any input, each refusal one sentence -----------------------------------

def _png(img: np.ndarray) -> bytes:
    ok, buf = cv2.imencode(".png", img)
    assert ok
    return buf.tobytes()


@pytest.mark.parametrize("w, h", [(1, 1), (1, 5000), (5000, 1)])
def test_tiny_images_are_422_not_500(client, w, h):
    """Item 4: 1x1 and 1x5000 images reached cv2.resize with an empty size in edges.py (500)."""
    detail = assert_error(estimate(client, client.ready_id, image=_png(np.zeros((h, w), np.uint8))), 422)
    assert f"{w} x {h}" in detail and "at least" in detail


def test_the_smallest_accepted_image_gets_an_answer(client):
    """Item 4: at the minimum size the pipeline runs (nothing to find there: found is false)."""
    from service.decode import MIN_IMAGE_SIDE_PX

    n = MIN_IMAGE_SIDE_PX
    for shape in [(n, n), (n, 2000), (2000, n)]:
        r = estimate(client, client.ready_id, image=_png(np.zeros(shape, np.uint8)),
                     camera={"fx": 500.0, "fy": 500.0, "cx": (shape[1] - 1) / 2, "cy": (shape[0] - 1) / 2})
        assert r.status_code == 200, r.text
        assert r.json()["found"] is False


def test_image_bomb_is_413_from_its_header(client):
    """Item 3: a 1 MB PNG of 20000 x 20000 is refused by its header (it was decoded first: 2.3 GB)."""
    from tests.test_decode import _png_header_only

    detail = assert_error(estimate(client, client.ready_id, image=_png_header_only(20000, 20000)), 413)
    assert "20000 x 20000" in detail


@pytest.mark.parametrize("camera, options, words", [
    ({**CAMERA, "fx": 1e15}, None, "fx is 1e+15 px, over"),
    ({**CAMERA, "fx": 1e300}, None, "fx is 1e+300 px"),
    ({**CAMERA, "fx": 1e-300}, None, "under 50 px"),
    ({**CAMERA, "fy": 12.0}, None, "not millimetres"),
    ({**CAMERA, "cx": 1e300}, None, "cx is 1e+300 px, outside this 1280 x 960 image"),
    ({**CAMERA, "cy": -40.0}, None, "principal point must lie in the image"),
    ({**CAMERA, "dist": [1e200, 0, 0, 0]}, None, "dist"),
    (CAMERA, {"distance_mm": 0.5},
     "distance_mm is 0.5, under 10 mm: distances are in millimetres (did you send metres?)"),
    (CAMERA, {"distance_mm": 1e300}, "over 20 m"),
    (CAMERA, {"distance_range_mm": [0.3, 0.9]}, "did you send metres"),
    (CAMERA, {"distance_range_mm": [300, 50000]}, "over 20 m"),
])
def test_implausible_camera_or_distance_is_422_with_the_likely_fix(client, image_bytes, camera, options,
                                                                   words):
    """Item 5: values that pass the schema but no real camera has (fx = 1e15, 1e300, 1e-300; cx = 1e300
    made coarse.py fail with a 500)."""
    r = estimate(client, client.ready_id, image=image_bytes, camera=camera, options=options)
    assert words in assert_error(r, 422)


def test_deeply_nested_json_is_422(client, image_bytes):
    """Item 6: 100,000 brackets (200 KB) made json.loads raise RecursionError (500)."""
    deep = "[" * 100_000 + "]" * 100_000
    assert "levels" in assert_error(estimate(client, client.ready_id, image=image_bytes, options=deep), 422)
    assert "levels" in assert_error(estimate(client, client.ready_id, image=image_bytes,
                                             camera='{"dist": ' + deep + "}"), 422)
    r = client.post("/models", files={"file": ("sprayer.stl", b"x")}, data={"templates": "{" * 50_000})
    assert_error(r, 422)
    # brackets inside strings are text, not nesting
    r = estimate(client, client.ready_id, image=image_bytes, options=json.dumps({"[" * 40: 1}))
    assert "distance" not in assert_error(r, 422)


def test_empty_camera_says_missing_or_empty(client, image_bytes):
    """Item 12: an empty camera part was reported as missing only."""
    r = client.post(f"/models/{client.ready_id}/estimate", files={"image": ("i.png", image_bytes)},
                    data={"camera": ""})
    assert "'camera' is missing or empty" in assert_error(r, 422)


def test_templates_null_names_the_json_type(client, sprayer_bytes):
    """Item 12: 'not NoneType' was Python's name for JSON's null."""
    detail = assert_error(client.post("/models", files={"file": ("sprayer.stl", sprayer_bytes)},
                                      data={"templates": "null"}), 422)
    assert "not null" in detail and "NoneType" not in detail
    detail = assert_error(client.post("/models", files={"file": ("sprayer.stl", sprayer_bytes)},
                                      data={"templates": "[1, 2]"}), 422)
    assert "not an array" in detail


def test_a_mesh_without_extension_is_read_by_content(client, sprayer_bytes):
    """Item 12: a file name without an extension got 415 although the bytes are a valid STL."""
    r = client.post("/models", files={"file": ("sprayer", sprayer_bytes)},  # a new id: decoded here
                    data={"symmetry": "x", "templates": json.dumps(GRID)})
    assert r.status_code == 202, r.text
    assert r.json()["extents_mm"] == pytest.approx([60.0, 200.0, 60.0], abs=0.01)


def test_405_lists_every_allowed_method(client):
    """Item 12: /models/{id} answers GET and DELETE; the Allow header named one of them."""
    r = client.put(f"/models/{client.ready_id}")
    detail = assert_error(r, 405)
    assert set(r.headers["allow"].replace(" ", "").split(",")) == {"GET", "DELETE"}
    assert "GET" in detail and "DELETE" in detail
    r = client.get("/models/x/estimate")
    assert assert_error(r, 405) and r.headers["allow"] == "POST"


def test_name_length_is_limited_and_long_ids_are_not_echoed(client, sprayer_bytes):
    """Item 12: a 100,000-character name was stored, a 60,000-character id echoed in the 404."""
    r = client.post("/models", files={"file": ("sprayer.stl", sprayer_bytes)}, data={"name": "n" * 100_000})
    assert "name" in assert_error(r, 422)
    long_id = "a" * 60_000
    detail = assert_error(client.get(f"/models/{long_id}"), 404)
    assert long_id not in detail and len(detail) < 300
    r = client.post("/models", files={"file": ("p" * 1000 + ".stl", sprayer_bytes)},
                    data={"symmetry": "z"})
    assert r.status_code == 202 and len(r.json()["name"]) <= 200


@pytest.mark.parametrize("body, content_type", [
    (b"--xyz\r\nContent-Disposition: form-data; name=\"camera\"\r\n\r\n" + b"a" * (1100 * 1024)
     + b"\r\n--xyz--\r\n",
     "multipart/form-data; boundary=xyz"),
    (b"garbage without any boundary", "multipart/form-data; boundary=xyz"),
    (b"--xyz\r\nno headers here\r\n\r\n--xyz--", "multipart/form-data; boundary=xyz"),
])
def test_multipart_parser_errors_are_400_sentences(client, body, content_type):
    """Item 12: the multipart parser's 400s ("Invalid multipart data.", "Part exceeded maximum size of
    1024KB.") are sentences that say how to send the form, and are in API.md's table."""
    r = client.post(f"/models/{client.ready_id}/estimate", content=body,
                    headers={"content-type": content_type})
    if r.status_code == 400:
        detail = assert_error(r, 400)
        assert "multipart/form-data" in detail and "send" in detail
    else:
        assert_error(r, 422)


# --- options.roi, max_instances, sort, plane: 422 with the fix -------------------------------------------

@pytest.mark.parametrize("options, words", [
    ({"roi": {"x": 10, "y": 10, "w": 0, "h": 50}}, "zero area"),
    ({"roi": [[0, 0], [100, 0]]}, "at least 3"),
    ({"roi": [[0, 0], [100, 100], [100, 0], [0, 100]]}, "crosses itself"),
    ({"roi": [[0, 0], [50, 50], [100, 100]]}, "zero area"),
    ({"roi": {"x": 5000, "y": 5000, "w": 100, "h": 100}}, "covers no pixel"),
    ({"max_instances": 51}, "max_instances"),
    ({"sort": "height"}, "supporting plane"),
    ({"plane": {"normal": [0, 0, 0], "d_mm": -500}}, "zero vector"),
    ({"plane": {"normal": [0, 0, -1], "d_mm": 500}}, "normal points away from the camera"),
    ({"plane": {"normal": [0, 0, -1], "d_mm": 0}}, "passes through the camera"),
    ({"plane": {"normal": [0, 0, 1], "d_mm": -500}}, "not in view"),
    ({"plane": {"normal": [0, 0, -1], "d_mm": -0.5}}, "did you send metres"),
    ({"plane": {"normal": [0, 0, -1], "d_mm": -1e6}}, "over 20 m"),
    ({"plane": {"normal": [0, 0, -1], "d_mm": -500}, "distance_mm": 500}, "give plane or distance_mm"),
    ({"plane": {"normal": [0, 0, -1], "d_mm": -500}, "plane_tolerance_mm": 0}, "plane_tolerance_mm"),
    ({"plane": {"normal": [0, 0, -1]}}, "d_mm"),
])
def test_bad_roi_or_instances_is_422_with_the_fix(client, image_bytes, options, words):
    assert words in assert_error(estimate(client, client.ready_id, image=image_bytes, options=options), 422)


# --- requests that sized a buffer by the part's apparent size: 422 before the search (service/bounds.py)

@pytest.mark.parametrize("options, words", [
    ({"distance_mm": 10}, ["options.distance_mm (10 mm)", "would reach the camera", "at least 243 mm"]),
    ({"distance_mm": 50}, ["options.distance_mm (50 mm)", "would reach the camera", "at least 243 mm"]),
    ({"distance_range_mm": [10, 2000]}, ["options.distance_range_mm (10 mm)", "would reach the camera"]),
    ({"plane": {"normal": [0, 0, -1], "d_mm": -10}}, ["The options field plane is at most 10 mm", "d_mm"]),
    ({"roi": [[0, 0], [1e15, 0], [0, 1e15]]}, ["roi has a coordinate of 1e+15 px"]),
])
def test_a_part_nearer_than_its_size_is_422_not_500(client, image_bytes, options, words):
    """distance_mm 10 or 50 put the 200 mm sprayer through the camera: level A's padded layout asked for
    86 TiB (MemoryError, 500). 243 mm: its reference point 100 mm from the origin, plus 143 mm where its
    109 mm bounding sphere appears 3840 px (4 x 960) across at the image's corner. The roi's corners were
    cast to int32 sixteenths of a pixel."""
    detail = assert_error(estimate(client, client.ready_id, image=image_bytes, options=options), 422)
    for w in words:
        assert w in detail


def test_a_focal_length_that_makes_the_part_huge_is_422_naming_fx(client, image_bytes):
    detail = assert_error(estimate(client, client.ready_id, image=image_bytes,
                                   camera={**CAMERA, "fx": 1e6, "fy": 1e6}), 422)
    assert "with fx 1e+06 px, more than the 3840 px the search allows in this 1280 x 960 image" in detail
    assert "check fx and fy" in detail


def test_the_same_part_at_a_plausible_distance_is_found(client, image_bytes):
    """The twin of the 422s above: the paper render's true distance (500 mm)."""
    r = estimate(client, client.ready_id, image=image_bytes, options={"distance_mm": 500})
    assert r.status_code == 200, r.text
    assert r.json()["found"] is True


def test_a_mesh_in_mm_uploaded_as_metres_is_422_naming_the_units(client, image_bytes, sprayer_bytes):
    """The sprayer read with units m is 200 m tall: the upload warns (202) and its estimate was a 500
    (MemoryError); now a 422 that names the units, while the same file in mm answers (the twin)."""
    r = client.post("/models", files={"file": ("sprayer.stl", sprayer_bytes)},
                    data={"symmetry": "y", "units": "m"})
    assert r.status_code == 202 and any("units=mm" in w for w in r.json()["warnings"]), r.text
    mid = r.json()["id"]
    assert wait_built(client, mid)["status"] == "ready"
    for options in ({}, {"distance_mm": 500}):
        detail = assert_error(estimate(client, mid, image=image_bytes, options=options), 422)
        assert "would reach the camera" in detail
        assert "upload the model again with its true units (it was read in m)" in detail
    r = estimate(client, client.ready_id, image=image_bytes)
    assert r.status_code == 200 and r.json()["found"] is True, r.text
