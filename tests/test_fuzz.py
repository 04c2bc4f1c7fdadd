"""A bounded schema fuzz (hypothesis) of every form part against the in-process app: whatever a client
sends, the answer is a 2xx or a 4xx with a one-sentence detail, never a 5xx.

Bounded by example count, not time: ``MAX_EXAMPLES`` per test, a fixed seed (``derandomize``), no
shrinking budget beyond hypothesis' default; the estimates use a small image and a known distance
so each takes milliseconds.
"""

from __future__ import annotations

import json
import warnings

import cv2
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from service.main import create_app
from service.settings import Settings
from tests.api_helpers import wait_built

with warnings.catch_warnings():
    warnings.filterwarnings("ignore", message="Using `httpx` with `starlette.testclient`")
    from fastapi.testclient import TestClient

MAX_EXAMPLES = 120
FUZZ = settings(max_examples=MAX_EXAMPLES, deadline=None, derandomize=True, database=None,
                suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])
GRID = {"tilt_step_deg": 30, "view_step_deg": 60}


def _image(w: int = 96, h: int = 72) -> bytes:
    img = np.full((h, w), 60, np.uint8)
    cv2.circle(img, (w // 2, h // 2), max(1, min(w, h) // 4), 200, -1)
    return cv2.imencode(".png", img)[1].tobytes()


IMAGE = _image()
IMAGES = [IMAGE, _image(1, 1), _image(1, 300), _image(300, 2), _image(32, 32)]

numbers = st.one_of(
    st.floats(allow_nan=False, allow_infinity=False),
    st.sampled_from([0, -1, 1e-300, 1e-6, 0.5, 10, 47.5, 95, 500, 1e6, 1e15, 1e300, -1e300, 2**63, 10**400]),
    st.integers(min_value=-(10**30), max_value=10**30),
)
json_values = st.recursive(
    st.one_of(st.none(), st.booleans(), numbers, st.text(max_size=20)),
    lambda inner: st.one_of(st.lists(inner, max_size=6),
                            st.dictionaries(st.text(max_size=12), inner, max_size=5)),
    max_leaves=12,
)
camera = st.fixed_dictionaries(
    {},
    optional={"fx": numbers, "fy": numbers, "cx": numbers, "cy": numbers,
              "dist": st.lists(numbers, min_size=0, max_size=9)},
)
options = st.fixed_dictionaries(
    {},
    optional={"distance_mm": numbers, "distance_range_mm": st.lists(numbers, max_size=3),
              "refine": st.one_of(st.booleans(), json_values), "top_k": numbers,
              "overlay": st.booleans()},
)


def _text(value) -> str:
    """JSON text of a value, with NaN/Infinity as JSON's non-standard words (clients send those)."""
    return json.dumps(value, allow_nan=True) if not isinstance(value, str) else value


def _sound(r) -> None:
    assert r.status_code < 500, r.text
    if r.status_code >= 400:
        detail = r.json()["detail"]
        assert isinstance(detail, str) and detail[-1] in ".?!" and "\n" not in detail, detail


@pytest.fixture(scope="module")
def client(tmp_path_factory, sprayer_bytes):
    s = Settings(cache_dir=tmp_path_factory.mktemp("fuzz-cache"), template_grid=GRID)
    with TestClient(create_app(s)) as c:
        r = c.post("/models", files={"file": ("sprayer.stl", sprayer_bytes)}, data={"symmetry": "y"})
        assert wait_built(c, r.json()["id"])["status"] == "ready"
        c.ready_id = r.json()["id"]
        yield c


@FUZZ
@given(cam=st.one_of(camera, camera, camera, json_values, st.text(max_size=40)),
       opts=st.one_of(options, options, json_values), image=st.sampled_from(IMAGES))
def test_estimate_never_answers_5xx(client, cam, opts, image):
    base = {"fx": 100.0, "fy": 100.0, "cx": 47.5, "cy": 35.5}
    if isinstance(cam, dict) and not (set(cam) - {"fx", "fy", "cx", "cy", "dist"}):
        cam = {**base, **cam}  # mostly well-formed, so the values reach the pipeline
    if isinstance(opts, dict) and "distance_mm" not in opts and "distance_range_mm" not in opts:
        opts = {**opts, "distance_mm": 400.0}
    r = client.post(f"/models/{client.ready_id}/estimate", files={"image": ("i.png", image)},
                    data={"camera": _text(cam), "options": _text(opts)})
    _sound(r)


@FUZZ
@given(name=st.one_of(st.none(), st.text(max_size=300)), units=st.one_of(st.sampled_from(["mm", "m", "in"]),
                                                                            st.text(max_size=5)),
       symmetry=st.text(max_size=5), templates=st.one_of(st.none(), json_values, st.text(max_size=30)),
       filename=st.text(max_size=30), content=st.binary(max_size=200))
def test_upload_never_answers_5xx(client, name, units, symmetry, templates, filename, content):
    data = {"units": units, "symmetry": symmetry}
    if name is not None:
        data["name"] = name
    if templates is not None:
        data["templates"] = _text(templates)
    r = client.post("/models", files={"file": (filename or "x", content)}, data=data)
    _sound(r)
    if r.status_code == 202:  # a tiny mesh that happened to be valid: do not leave a build behind
        client.delete(f"/models/{r.json()['id']}")


@FUZZ
@given(path=st.text(alphabet=st.characters(min_codepoint=0x20, blacklist_categories=("Cs", "Cc"),
                                         blacklist_characters="?#\x7f"), max_size=80),
       method=st.sampled_from(["GET", "POST", "PUT", "DELETE", "PATCH"]))
def test_any_path_never_answers_5xx(client, path, method):
    r = client.request(method, "/models/" + path)
    _sound(r)
