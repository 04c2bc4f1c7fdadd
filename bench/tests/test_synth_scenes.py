"""bench/synth_scenes.py: the written ground truth is the geometry of the image (3 tiny scenes)."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from bench import synth_scenes as S  # noqa: N812

try:
    from service.vision.geometry.frames import Pose
    from service.vision.geometry.render import render
except ImportError:
    from service.vision.frames import Pose
    from service.vision.render import render

W, H = 320, 240
SEED = 11


@pytest.fixture(scope="module")
def written(data_dir, tmp_path_factory):
    out = tmp_path_factory.mktemp("synth")
    S.generate(out, 3, SEED, (W, H), list(S.DEFAULT_MODELS), absent_frac=0.34, min_visible=0.5, quiet=True)
    return out, [json.loads(line) for line in (out / "gt.jsonl").read_text().splitlines()]


def test_set_folder_format(written):
    out, gts = written
    assert len(gts) == 3
    assert json.loads((out / "meta.json").read_text())["n_images"] == 3
    for g in gts:
        img = cv2.imread(str(out / g["image"]))
        assert img.shape == (H, W, 3)
        assert (out / "models" / f"{g['model']}.stl").is_file()
        assert (g["width"], g["height"]) == (W, H) and np.shape(g["K"]) == (3, 3)
        assert g["symmetry"] == S.SYMMETRY[g["model"]]
        if g.get("absent"):
            assert "R" not in g and "t_mm" not in g and g["visible_fraction"] == 0.0
        else:
            assert np.shape(g["R"]) == (3, 3) and len(g["t_mm"]) == 3 and 0.5 <= g["visible_fraction"] <= 1


@pytest.mark.parametrize("index", [1, 2, 3])
def test_ground_truth_is_the_image(data_dir, index):
    models = list(S.DEFAULT_MODELS)
    s = S.scene(SEED, index, W, H, models, absent_frac=0.0, clean=True)
    g = s["gt"]
    assert not g.get("absent")
    mesh = S.load_model(g["model"])
    K, R, t = np.array(g["K"]), np.array(g["R"]), np.array(g["t_mm"])
    # the part rendered alone at the written pose is the generator's part mask (same supersampling),
    # and agrees with a plain pixel-centre render
    full = render(mesh.V, mesh.F, Pose(R, t), K, (W, H), supersample=S.SUPERSAMPLE).mask
    assert full.sum() > 50 and np.array_equal(full, s["full_mask"])
    plain = render(mesh.V, mesh.F, Pose(R, t), K, (W, H)).mask
    assert (plain & full).sum() / (plain | full).sum() > 0.85
    c = K @ (R @ mesh.centre + t)
    assert 0 <= c[0] / c[2] < W and 0 <= c[1] / c[2] < H
    vis = s["visible_mask"]
    assert not (vis & ~full).any()
    assert g["visible_fraction"] == pytest.approx(vis.sum() / full.sum(), abs=1e-4)
    # the image changes exactly where the part is: the same scene without it differs only on the part
    # (one pixel of anti-aliasing around it) and on its cast shadow
    without = S.scene(SEED, index, W, H, models, absent_frac=0.0, clean=True, omit_target=True)["image"]
    d = np.abs(s["image"].astype(int) - without.astype(int)).max(axis=2)
    diff = d > 0
    around = cv2.dilate(full.astype(np.uint8), np.ones((3, 3), np.uint8)) > 0
    shadow = s["target_shadow"]
    assert not (diff & ~around & (shadow == 0)).any()
    assert not ((d > 1) & ~around & (shadow < 1e-3)).any()  # a faint shadow tail may round 1 level off
    assert (diff & vis).sum() >= 0.5 * vis.sum()
    near_vis = cv2.dilate(vis.astype(np.uint8), np.ones((3, 3), np.uint8)) > 0
    assert not (diff & full & ~near_vis).any()  # the hidden part of the part leaves the image unchanged


def test_absent_scene_and_determinism(data_dir, written):
    out, gts = written
    s = S.scene(SEED, 1, W, H, list(S.DEFAULT_MODELS), absent_frac=1.0)
    assert s["gt"]["absent"] is True and "R" not in s["gt"] and s["full_mask"] is None
    assert s["gt"]["model"] not in s["gt"]["distractors"]
    again = S.scene(SEED, 1, W, H, list(S.DEFAULT_MODELS), absent_frac=0.34)
    assert json.loads(json.dumps(again["gt"])) == {k: v for k, v in gts[0].items() if k != "image"}
    assert np.array_equal(again["image"], cv2.imread(str(out / gts[0]["image"])))


def test_clutter_occlusion_hides_the_same_target_and_counts_it(data_dir):
    """``occlusion="clutter"``: the same target (model, pose, camera) as the plain scene, an occluder
    in front of most of them that lowers the visible fraction (never under 0.5: the bisection stops on
    its visible side), and the written fraction is the masks' own ratio."""
    models = list(S.DEFAULT_MODELS)
    added = 0
    for index in range(1, 7):
        plain = S.scene(SEED, index, W, H, models, absent_frac=0.0, clean=True)
        occl = S.scene(SEED, index, W, H, models, absent_frac=0.0, clean=True, occlusion="clutter")
        g0, g = plain["gt"], occl["gt"]
        assert (g["model"], g["K"], g["R"], g["t_mm"]) == (g0["model"], g0["K"], g0["R"], g0["t_mm"])
        assert np.array_equal(plain["full_mask"], occl["full_mask"])
        vis = occl["visible_mask"]
        assert g["visible_fraction"] == pytest.approx(vis.sum() / occl["full_mask"].sum(), abs=1e-4)
        assert not (vis & ~plain["visible_mask"]).any()  # an occluder only hides
        if g["occluders_added"]:
            added += 1
            assert 0.5 <= g["visible_fraction"] < g0["visible_fraction"]
        else:
            assert g["visible_fraction"] == g0["visible_fraction"]
    assert added >= 2
