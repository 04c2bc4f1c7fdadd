"""The command line (``python -m service build | estimate``) as a newcomer meets it: the shipped
example camera, one-line errors for missing files, a progress line while building, and the overlay
written as a PNG file instead of base64 into the terminal."""

from __future__ import annotations

import io
import json
import threading
from pathlib import Path

import cv2
import numpy as np
import pytest

from service.__main__ import _progress, main
from service.schemas import CellCamera
from service.stores import open_store
from tests.scenes import L_BLOCK_GRID, l_block
from tests.tolerances import COARSE_XY_MM

ROOT = Path(__file__).resolve().parents[1]
EXAMPLE_CAMERA = ROOT / "examples" / "cam.json"
GRID = json.dumps({"tilt_step_deg": 15, "view_step_deg": 45})


def test_example_camera_is_the_paper_renders_camera(paper_gt):
    cam = CellCamera.model_validate_json(EXAMPLE_CAMERA.read_text())
    K = np.array(paper_gt["K"])
    assert (cam.fx, cam.fy, cam.cx, cam.cy) == (K[0, 0], K[1, 1], K[0, 2], K[1, 2])
    assert (cam.width, cam.height) == (paper_gt["width"], paper_gt["height"])


def test_missing_camera_file_says_file_not_found(tmp_path, capsys):
    code = main(["--cache-dir", str(tmp_path), "estimate", "part.stl", "image.png", "--camera", "cam.json"])
    assert code == 2
    err = capsys.readouterr().err
    assert err.startswith("error: camera file not found: cam.json (give a JSON file such as "
                          "examples/cam.json")
    assert "not valid JSON" not in err


def test_missing_image_and_mesh_files_say_file_not_found(tmp_path, capsys):
    code = main(["--cache-dir", str(tmp_path), "estimate", "part.stl", "nothere.png",
                 "--camera", str(EXAMPLE_CAMERA)])
    assert code == 2
    assert capsys.readouterr().err.startswith("error: image file not found: nothere.png")
    assert main(["--cache-dir", str(tmp_path), "build", "nothere.stl"]) == 2
    assert capsys.readouterr().err.startswith("error: mesh file not found: nothere.stl")


def test_camera_text_that_is_not_json_is_still_a_json_error(tmp_path, capsys):
    assert main(["--cache-dir", str(tmp_path), "estimate", "p.stl", "i.png", "--camera", '{"fx": 1,']) == 2
    assert "The camera part is not valid JSON" in capsys.readouterr().err


@pytest.mark.parametrize("camera, options, words", [
    ({"fx": 8.0, "fy": 8.0, "cx": 39.5, "cy": 29.5}, {}, "not millimetres"),
    ({"fx": 900.0, "fy": 900.0, "cx": 319.5, "cy": 29.5}, {}, "cx is 319.5 px, outside this 80 x 60 image"),
    ({"fx": 900.0, "fy": 900.0, "cx": 39.5, "cy": 29.5}, {"distance_mm": 0.5}, "did you send metres"),
])
def test_the_clis_estimate_is_held_to_the_plausibility_bounds(camera, options, words):
    """``python -m service estimate`` runs ``cell_io.estimate_result`` as the API does, so the bounds
    (service/bounds.py) refuse an implausible camera or distance there too, once the image is decoded
    and before the search (which is why no bank is needed here)."""
    from service.cell_io import estimate_result
    from service.errors import UnprocessableError
    from service.schemas import Options

    ok, png = cv2.imencode(".png", np.zeros((60, 80), np.uint8))
    assert ok
    with pytest.raises(UnprocessableError) as e:
        estimate_result({"id": "m1"}, None, png.tobytes(), CellCamera.model_validate(camera),
                        Options.model_validate(options), max_pixels=10**6)
    assert words in e.value.detail


def test_build_progress_line(tmp_path):
    """The line a terminal shows while a build runs: overwritten in place, cleared at the end."""
    with open_store(tmp_path) as store:
        store.create({"id": "m1", "status": "building", "progress": 0.5}, b"mesh")
    out, done = io.StringIO(), threading.Event()
    t = threading.Thread(target=_progress, args=(tmp_path, "m1", done, out))
    t.start()
    while "%" not in out.getvalue():
        t.join(0.1)
    done.set()
    t.join()
    text = out.getvalue()
    assert text.startswith("\rbuilding templates of m1: building  50%")
    assert text.endswith("\r\033[K")


@pytest.mark.slow
def test_estimate_writes_the_overlay_png(tmp_path, data_dir, capsys):
    overlay = tmp_path / "overlay.png"
    code = main(["--cache-dir", str(tmp_path / "cache"), "estimate", str(data_dir / "models" / "sprayer.stl"),
                 str(data_dir / "paper" / "images" / "0001.png"), "--camera", str(EXAMPLE_CAMERA),
                 "--templates", GRID, "--options", '{"distance_mm": 500}', "--overlay-out", str(overlay)])
    captured = capsys.readouterr()
    assert code == 0, captured.err
    result = json.loads(captured.out)
    assert result["found"] is True and result["overlay_png_base64"] is None
    assert f"overlay written to {overlay}" in captured.err
    img = cv2.imread(str(overlay))
    assert img.shape == (960, 1280, 3)


def test_build_then_estimate_prints_the_api_json(tmp_path, data_dir, paper_gt, capsys):
    mesh = str(data_dir / "models" / "sprayer.stl")
    grid = '{"tilt_step_deg": 6}'
    assert main(["--cache-dir", str(tmp_path), "build", mesh, "--symmetry", "y", "--templates", grid]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["status"] == "ready" and info["symmetry"] == {"type": "continuous", "axis": [0.0, 1.0, 0.0]}
    K = paper_gt["K"]
    camera = json.dumps({"fx": K[0][0], "fy": K[1][1], "cx": K[0][2], "cy": K[1][2]})
    image = str(data_dir / "paper" / paper_gt["image"])
    assert main(["--cache-dir", str(tmp_path), "estimate", mesh, image, "--symmetry", "y", "--templates",
                 grid, "--camera", camera, "--options", '{"distance_mm": 500, "refine": false}']) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["model_id"] == info["id"] and out["found"]
    t_mm = np.array(out["coarse"]["t_mm"])
    assert np.all(np.abs(t_mm[:2] - np.array(paper_gt["t_mm"])[:2]) <= COARSE_XY_MM)


def test_the_clis_estimate_is_judged_on_the_model_s_reference_photos(tmp_path, data_dir, paper_gt, capsys,
                                                                      monkeypatch):
    """A reference photo stored in the cache (as POST /models/{id}/references stores it) reaches the
    CLI's estimate: its verdict reads the taught colours (evidence.appearance). (The paper sprayer is a
    plain part, and one photo cannot be checked against another: here every taught part's colours are
    used.)"""
    from service import references
    from service.schemas import Transform
    from service.vision.model import appearance

    monkeypatch.setattr(appearance.Appearance, "used", property(lambda self: True))
    mesh = str(data_dir / "models" / "sprayer.stl")
    assert main(["--cache-dir", str(tmp_path), "build", mesh, "--symmetry", "y", "--templates", GRID]) == 0
    mid = json.loads(capsys.readouterr().out)["id"]
    K = paper_gt["K"]
    camera = {"fx": K[0][0], "fy": K[1][1], "cx": K[0][2], "cy": K[1][2]}
    image = data_dir / "paper" / paper_gt["image"]
    args = ["--cache-dir", str(tmp_path), "estimate", mesh, str(image), "--symmetry", "y", "--templates",
            GRID, "--camera", json.dumps(camera), "--options", '{"distance_mm": 500}']
    assert main(args) == 0
    assert "appearance" not in json.loads(capsys.readouterr().out)["verdict"]["evidence"]
    with open_store(tmp_path) as store:
        record = store.get(mid)
        pose = Transform(R=paper_gt["R"], t_mm=paper_gt["t_mm"])
        references.add_reference(store, record, store.bank(mid), image.read_bytes(), CellCamera(**camera),
                                 None, pose, max_pixels=10**8)
    assert main(args) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["found"] and out["verdict"]["evidence"]["appearance"] > 0


def test_build_calibrates_the_part_for_a_plane_as_the_service_does(tmp_path, capsys, monkeypatch):
    monkeypatch.setenv("POSE_PLANE_CALIBRATION_SCENES", "1")
    mesh = tmp_path / "l_block.stl"
    l_block().export(mesh)
    assert main(["--cache-dir", str(tmp_path / "cache"), "build", str(mesh), "--symmetry", "none",
                 "--templates", json.dumps(L_BLOCK_GRID)]) == 0
    out = capsys.readouterr()
    assert "calibrating for a plane: scene 1 of 1" in out.err
    info = json.loads(out.out)["plane_calibration"]
    assert info["status"] == "calibrated" and info["scenes"] == 1 and info["progress"] == 1.0
    with open_store(tmp_path / "cache") as store:  # kept: a second build finds it done
        assert store.get(json.loads(out.out)["id"])["plane_calibration"]["status"] == "calibrated"
