"""Rasteriser known answers: projection centre, cylinder and sphere silhouettes, depth, shading."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from service.vision.geometry.camera import Intrinsics
from service.vision.geometry.frames import Pose, Ry
from service.vision.geometry.render import render, render_shaded
from tests.tolerances import RENDER_CENTRE_PX, RENDER_DEPTH_MM, RENDER_EXTENT_PX

INTR = Intrinsics(fx=1000.0, fy=1000.0, cx=319.3, cy=241.7)
SIZE = (640, 480)


def test_origin_projects_to_principal_point():
    # A square patch centred on the origin, facing the camera, at [I | (0, 0, z)].
    sq = np.array([[-5.0, -5.0, 0.0], [5.0, -5.0, 0.0], [5.0, 5.0, 0.0], [-5.0, 5.0, 0.0]])
    faces = np.array([[0, 1, 2], [0, 2, 3]])
    r = render(sq, faces, Pose(np.eye(3), np.array([0.0, 0.0, 400.0])), INTR, SIZE, supersample=4)
    vv, uu = np.mgrid[0:SIZE[1], 0:SIZE[0]]
    c = r.coverage
    centroid = np.array([(c * uu).sum() / c.sum(), (c * vv).sum() / c.sum()])
    np.testing.assert_allclose(centroid, [INTR.cx, INTR.cy], atol=RENDER_CENTRE_PX)
    assert c.sum() == pytest.approx((1000.0 * 10.0 / 400.0) ** 2, rel=1e-2)


def test_cylinder_side_on_is_a_rectangle_of_the_right_size():
    radius, length, z = 20.0, 120.0, 500.0
    cyl = trimesh.creation.cylinder(radius=radius, height=length, sections=256)
    pose = Pose(Ry(90.0), np.array([0.0, 0.0, z]))  # axis along camera x
    r = render(cyl.vertices, cyl.faces, pose, INTR, SIZE, supersample=4)
    row = int(round(INTR.cy))
    col = int(round(INTR.cx))
    width = r.coverage[row].sum()
    height = r.coverage[:, col].sum()
    f = INTR.fx
    # Exact silhouette extents: the near rims of the end caps / the tangent rays to the side.
    assert width == pytest.approx(f * length / (z - radius), abs=RENDER_EXTENT_PX + 0.05)
    assert height == pytest.approx(2 * f * radius / np.sqrt(z**2 - radius**2), abs=RENDER_EXTENT_PX)
    assert width == pytest.approx(f * length / z, abs=1.0 + f * length / z * radius / z)
    # Rectangular: every row is between the far-rim and the near-rim width (perspective).
    rows = np.nonzero(r.mask.any(axis=1))[0]
    widths = r.coverage[rows[1:-1]].sum(axis=1)
    assert widths.min() >= f * length / (z + radius) - 1.0
    assert widths.max() <= width + RENDER_EXTENT_PX


def test_sphere_border_is_a_circle_and_depth_at_centre():
    radius, z = 100.0, 600.0
    sph = trimesh.creation.icosphere(subdivisions=6, radius=radius)
    intr = Intrinsics(fx=800.0, fy=800.0, cx=320.0, cy=240.0)
    r = render(sph.vertices, sph.faces, Pose(np.eye(3), np.array([0.0, 0.0, z])), intr, SIZE, supersample=4)
    rho = 800.0 * radius / np.sqrt(z**2 - radius**2)
    assert np.sqrt(r.coverage.sum() / np.pi) == pytest.approx(rho, abs=RENDER_EXTENT_PX)
    # Circular: boundary pixels of the mask are all at distance rho from the centre (to a pixel).
    m = r.mask
    edge = m & ~(np.roll(m, 1, 0) & np.roll(m, -1, 0) & np.roll(m, 1, 1) & np.roll(m, -1, 1))
    vv, uu = np.nonzero(edge)
    d = np.hypot(uu - 320.0, vv - 240.0)
    assert np.abs(d - rho).max() < 1.0
    assert r.depth_mm[240, 320] == pytest.approx(z - radius, abs=RENDER_DEPTH_MM)
    assert np.isinf(r.depth_mm[0, 0]) and r.face_id[0, 0] == -1
    n = r.normal_cam[240, 320]
    np.testing.assert_allclose(n, [0.0, 0.0, -1.0], atol=1e-2)


def test_supersampled_and_plain_masks_agree_off_the_border(sprayer_mesh):
    pose = Pose.from_euler_xyz_deg([30.0, 0.0, 20.0], [0.0, -60.0, 500.0])
    r1 = render(sprayer_mesh.vertices, sprayer_mesh.faces, pose, INTR, SIZE)
    r4 = render(sprayer_mesh.vertices, sprayer_mesh.faces, pose, INTR, SIZE, supersample=4)
    differ = r1.mask != r4.mask
    assert differ.sum() < 0.02 * r1.mask.sum()
    both = r1.mask & r4.mask
    # The supersampled depth is the nearest sub-sample: equal up to the slope over half a pixel
    # (more only at internal occlusion steps).
    assert np.median(np.abs(r1.depth_mm[both] - r4.depth_mm[both])) < 1.0


def test_culls_geometry_behind_the_camera():
    sph = trimesh.creation.icosphere(subdivisions=2, radius=10.0)
    r = render(sph.vertices, sph.faces, Pose(np.eye(3), np.array([0.0, 0.0, -50.0])), INTR, SIZE)
    assert not r.mask.any()


def test_shaded_object_is_brighter_than_background(sprayer_mesh):
    pose = Pose.from_euler_xyz_deg([20.0, 0.0, 0.0], [0.0, -100.0, 500.0])
    img = render_shaded(sprayer_mesh.vertices, sprayer_mesh.faces, pose, INTR, SIZE, background=70)
    r = render(sprayer_mesh.vertices, sprayer_mesh.faces, pose, INTR, SIZE)
    assert img.dtype == np.uint8 and img.shape == (SIZE[1], SIZE[0])
    inner = (r.mask & np.roll(r.mask, 2, 0) & np.roll(r.mask, -2, 0) & np.roll(r.mask, 2, 1)
             & np.roll(r.mask, -2, 1))
    outer = ~(r.mask | np.roll(r.mask, 1, 0) | np.roll(r.mask, -1, 0) | np.roll(r.mask, 1, 1)
              | np.roll(r.mask, -1, 1))  # off the anti-aliased rim
    assert img[inner].min() >= 120 and img[outer].max() == 70
