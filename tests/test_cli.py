"""The command line (service/__main__.py) without HTTP: build, then estimate, print the API's JSON."""

from __future__ import annotations

import json

import numpy as np

from service.__main__ import main
from tests.tolerances import COARSE_XY_MM


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
