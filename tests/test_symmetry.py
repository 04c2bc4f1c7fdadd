"""Continuous rotational symmetry detection on the development models and on synthetic solids."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from service.vision.geometry.frames import R_between
from service.vision.model.symmetry import SYMMETRY_THRESHOLD, detect_symmetry, score_candidates
from tests.tolerances import SYMMETRY_AXIS_DEG, SYMMETRY_POINT_MM


def _angle_deg(a, b):
    return float(np.degrees(np.arccos(np.clip(abs(np.dot(a, b)), -1.0, 1.0))))


def _distance_to_axis(p, axis, point):
    d = np.asarray(p, float) - point
    return float(np.linalg.norm(d - (d @ axis) * axis))


def test_sprayer_axis_is_plus_y_through_the_origin(sprayer_mesh):
    found = detect_symmetry(sprayer_mesh)
    assert found is not None
    axis, point = found
    np.testing.assert_allclose(axis, [0.0, 1.0, 0.0], atol=1e-12)  # snapped, positive sign
    assert _distance_to_axis([0.0, 0.0, 0.0], axis, point) < SYMMETRY_POINT_MM  # origin at the base centre


def test_tless24_axis_is_z(data_dir):
    mesh = trimesh.load(data_dir / "models" / "tless_24.ply", force="mesh")
    found = detect_symmetry(mesh)
    assert found is not None
    axis, point = found
    assert _angle_deg(axis, [0.0, 0.0, 1.0]) < SYMMETRY_AXIS_DEG
    assert _distance_to_axis([0.0, 0.0, 0.0], axis, point) < SYMMETRY_POINT_MM


@pytest.mark.parametrize("name", ["tless_06.ply", "lbracket.stl", "flange.stl"])
def test_parts_without_continuous_symmetry(data_dir, name):
    mesh = trimesh.load(data_dir / "models" / name, force="mesh")
    assert detect_symmetry(mesh) is None
    assert score_candidates(mesh)[0].score > 2 * SYMMETRY_THRESHOLD  # a clear margin, not a near miss


def test_tilted_off_centre_cylinder_axis_is_found():
    cyl = trimesh.creation.cylinder(radius=15.0, height=80.0, sections=96)
    # A stepped shaft so that the principal axes are well defined: add a smaller coaxial cylinder.
    boss = trimesh.creation.cylinder(radius=8.0, height=30.0, sections=96)
    boss.apply_translation([0.0, 0.0, 55.0])
    shaft = trimesh.util.concatenate([cyl, boss])
    axis_true = np.array([0.3, -0.5, 0.81])
    axis_true /= np.linalg.norm(axis_true)
    R = R_between([0.0, 0.0, 1.0], axis_true)
    offset = np.array([12.0, -7.0, 30.0])
    shaft.vertices = shaft.vertices @ R.T + offset
    found = detect_symmetry(shaft)
    assert found is not None
    axis, point = found
    assert _angle_deg(axis, axis_true) < SYMMETRY_AXIS_DEG
    assert _distance_to_axis(offset, axis, point) < SYMMETRY_POINT_MM
    assert axis[np.argmax(np.abs(axis))] > 0  # sign convention


def test_box_and_hexagonal_prism_are_not_revolved():
    assert detect_symmetry(trimesh.creation.box([30.0, 40.0, 90.0])) is None
    hexagon = trimesh.creation.cylinder(radius=20.0, height=60.0, sections=6)
    assert detect_symmetry(hexagon) is None
