"""Borderline templates: known-answer borders, back-projection, grids, bank round trip, bad options."""

from __future__ import annotations

import io

import numpy as np
import pytest
import trimesh

from service.vision.bank import TemplateBank
from service.vision.geometry.camera import Intrinsics, project
from service.vision.geometry.frames import Pose, R_from_rotvec, Rx, Ry, rotation_angle_deg
from service.vision.geometry.silhouette import border_at_pose
from service.vision.model.grid import (
    GRID_DEFAULTS,
    fibonacci_directions,
    grid_rotations,
    look_from_R,
    merge_grid,
)
from service.vision.model.templates import build_bank, template_camera, template_pose
from tests.tolerances import (
    BACKPROJECT_PX,
    BORDER_RADIAL_PX,
    BORDER_THETA_MAX_DEG,
    SCANLINE_COVERS_CONTOUR_PX,
    SCANLINE_ON_CONTOUR_PX,
    SPIN_INVARIANCE_PX,
    TRACED_RADIAL_PX,
    TRACED_THETA_MAX_DEG,
    TRACED_THETA_MEAN_DEG,
)

INTR = Intrinsics(fx=800.0, fy=800.0, cx=320.3, cy=240.6)
SIZE = (640, 480)


@pytest.fixture(scope="module")
def sprayer_bank(sprayer_mesh):
    fractions = []
    bank = build_bank(sprayer_mesh, grid={"tilt_step_deg": 10.0}, progress=fractions.append)
    return bank, fractions


def _angle_diff(a, b):
    return np.abs((a - b + np.pi / 2) % np.pi - np.pi / 2)


def _densify(uv, max_gap_px=3.0, n=10):
    """Points every 1/n of the way between consecutive border points (contours are closed chains)."""
    nxt = np.roll(uv, -1, axis=0)
    keep = np.linalg.norm(nxt - uv, axis=1) < max_gap_px
    t = np.arange(n)[None, :, None] / n
    return (uv[keep, None, :] * (1 - t) + nxt[keep, None, :] * t).reshape(-1, 2)


def border_distance_px(a, b):
    """Largest distance from a border point of either set to the other set's polyline."""
    from scipy.spatial import cKDTree

    return max(cKDTree(_densify(b)).query(a)[0].max(), cKDTree(_densify(a)).query(b)[0].max())


@pytest.mark.parametrize("supersample", [1, 2, 4])
def test_sphere_border_is_the_tangent_circle(supersample):
    sph = trimesh.creation.icosphere(subdivisions=6, radius=100.0)
    z = 600.0
    uv, theta, p_obj = border_at_pose(sph.vertices, sph.faces, Pose(np.eye(3), np.array([0.0, 0.0, z])), INTR,
                                      SIZE, supersample=supersample, spacing_px=1.0)
    rho = INTR.fx * 100.0 / np.sqrt(z**2 - 100.0**2)
    d = uv - [INTR.cx, INTR.cy]
    r = np.hypot(d[:, 0], d[:, 1])
    assert np.abs(r - rho).max() < BORDER_RADIAL_PX
    assert abs(len(uv) - 2 * np.pi * rho) < 0.03 * 2 * np.pi * rho  # ~1 px spacing
    tangent = np.arctan2(d[:, 1], d[:, 0]) + np.pi / 2
    assert np.degrees(_angle_diff(theta, tangent)).max() < BORDER_THETA_MAX_DEG
    assert ((theta >= 0) & (theta < np.pi)).all()
    # The 3D points are on the sphere's rim (its tessellated edges), on the rays through the border.
    np.testing.assert_allclose(np.linalg.norm(p_obj, axis=1), 100.0, atol=0.02)
    np.testing.assert_allclose(project(p_obj + [0.0, 0.0, z], INTR.K), uv, atol=BACKPROJECT_PX)


def test_traced_border_without_snapping_is_subpixel():
    sph = trimesh.creation.icosphere(subdivisions=6, radius=100.0)
    z = 600.0
    uv, theta, p_obj = border_at_pose(sph.vertices, sph.faces, Pose(np.eye(3), np.array([0.0, 0.0, z])), INTR,
                                      SIZE, supersample=4, snap=False)
    rho = INTR.fx * 100.0 / np.sqrt(z**2 - 100.0**2)
    d = uv - [INTR.cx, INTR.cy]
    assert np.abs(np.hypot(d[:, 0], d[:, 1]) - rho).max() < TRACED_RADIAL_PX
    err = np.degrees(_angle_diff(theta, np.arctan2(d[:, 1], d[:, 0]) + np.pi / 2))
    assert err.mean() < TRACED_THETA_MEAN_DEG and err.max() < TRACED_THETA_MAX_DEG
    # Without snapping the 3D point is on the ray at the depth of the nearest covered sub-pixel.
    np.testing.assert_allclose(np.linalg.norm(p_obj, axis=1), 100.0, atol=0.3)
    np.testing.assert_allclose(project(p_obj + [0.0, 0.0, z], INTR.K), uv, atol=BACKPROJECT_PX)


def test_open_mesh_border_is_traced():
    # A mesh with a hole is not closed: no culling, no snapping, still a sub-pixel border.
    sph = trimesh.creation.icosphere(subdivisions=5, radius=100.0)
    keep = sph.triangles_center[:, 2] < 90.0  # cut a cap off the far side
    open_mesh = trimesh.Trimesh(sph.vertices, sph.faces[keep], process=False)
    from service.vision.geometry.silhouette import mesh_topology

    assert not mesh_topology(open_mesh.vertices, open_mesh.faces).closed
    assert mesh_topology(sph.vertices, sph.faces).closed
    pose = Pose(np.eye(3), np.array([0.0, 0.0, 600.0]))
    uv, _, _ = border_at_pose(open_mesh.vertices, open_mesh.faces, pose, INTR, SIZE, supersample=4)
    rho = INTR.fx * 100.0 / np.sqrt(600.0**2 - 100.0**2)
    d = uv - [INTR.cx, INTR.cy]
    assert np.abs(np.hypot(d[:, 0], d[:, 1]) - rho).max() < TRACED_RADIAL_PX


def test_cylinder_side_on_border_is_a_rectangle():
    radius, length, z = 20.0, 120.0, 500.0
    cyl = trimesh.creation.cylinder(radius=radius, height=length, sections=256)
    pose = Pose(Ry(90.0), np.array([0.0, 0.0, z]))
    uv, theta, _ = border_at_pose(cyl.vertices, cyl.faces, pose, INTR, SIZE, supersample=4)
    half_h = INTR.fy * radius / np.sqrt(z**2 - radius**2)
    half_w = INTR.fx * (length / 2) / (z - radius)
    # Long sides: points well away from the ends lie on v = cy +- half_h, horizontal.
    side = np.abs(uv[:, 0] - INTR.cx) < half_w - 10
    dv = np.abs(np.abs(uv[side, 1] - INTR.cy) - half_h)
    assert dv.max() < BORDER_RADIAL_PX
    assert np.degrees(_angle_diff(theta[side], 0.0)).max() < BORDER_THETA_MAX_DEG
    # Ends: at the centre row the extreme u is the near rim of the caps.
    mid = np.abs(uv[:, 1] - INTR.cy) < 1.5
    assert np.abs(np.abs(uv[mid, 0] - INTR.cx) - half_w).max() < BORDER_RADIAL_PX + 0.05


def test_spinning_the_sprayer_about_its_axis_leaves_its_border_unchanged(sprayer_mesh):
    K = np.array([[1100.0, 0.0, 643.0], [0.0, 1100.0, 477.0], [0.0, 0.0, 1.0]])
    base = Pose.from_euler_xyz_deg([35.0, 0.0, 20.0], [30.0, -40.0, 500.0])
    uv0, _, _ = border_at_pose(sprayer_mesh.vertices, sprayer_mesh.faces, base, K, (1280, 960))
    for spin in (23.0, 77.0, 140.0, 251.0):
        pose = Pose(base.R @ Ry(spin), base.t_mm)
        uv, _, _ = border_at_pose(sprayer_mesh.vertices, sprayer_mesh.faces, pose, K, (1280, 960))
        assert border_distance_px(uv, uv0) < SPIN_INVARIANCE_PX


def test_border_cut_by_the_image_frame_drops_frame_points(sprayer_mesh):
    pose = Pose(Rx(0.0), np.array([0.0, -100.0, 500.0]))  # the top half leaves the image
    uv, _, _ = border_at_pose(sprayer_mesh.vertices, sprayer_mesh.faces, pose, INTR, (640, 200))
    assert len(uv) > 100
    assert uv[:, 1].max() < 200 - 1.0


def test_sprayer_bank_layout(sprayer_bank):
    bank, fractions = sprayer_bank
    np.testing.assert_allclose(bank.symmetry_axis_obj, [0.0, 1.0, 0.0])
    np.testing.assert_allclose(bank.symmetry_point_obj[[0, 2]], 0.0, atol=1e-6)  # the axis is x = z = 0
    tilts = np.arange(-90.0, 90.0 + 1e-9, 10.0)
    assert bank.n_templates == len(tilts)
    np.testing.assert_allclose(bank.view_params_deg[:, 0], tilts)
    np.testing.assert_allclose(bank.view_params_deg[:, 1], 0.0)
    for k, t in enumerate(tilts):
        np.testing.assert_allclose(bank.R_tpl_obj[k], Rx(t), atol=1e-12)
    assert bank.offsets[0] == 0 and bank.offsets[-1] == len(bank.xy_n) and (np.diff(bank.offsets) > 100).all()
    assert bank.xy_n.dtype == bank.p_obj.dtype == bank.theta_rad.dtype == np.float32
    assert bank.faces.dtype == np.int32 and bank.vertices_mm.dtype == np.float32
    assert ((bank.theta_rad >= 0) & (bank.theta_rad < np.pi)).all()
    np.testing.assert_allclose(bank.centre_obj, [0.0, 100.0, 0.0], atol=1e-6)
    np.testing.assert_allclose(bank.extents_mm, [60.0, 200.0, 60.0], atol=1e-6)
    assert 200.0 < bank.diameter_mm < np.linalg.norm([60.0, 200.0, 60.0]) + 1e-6
    assert bank.grid["tilt_step_deg"] == 10.0 and bank.grid["render_px"] == GRID_DEFAULTS["render_px"]
    assert fractions == sorted(fractions) and fractions[-1] == 1.0 and len(fractions) == bank.n_templates
    assert merge_grid(bank.grid) == bank.grid  # the recorded options are valid options


def test_template_points_back_project(sprayer_bank):
    bank, _ = sprayer_bank
    intr, _ = template_camera(bank)
    for k in range(bank.n_templates):
        pose = template_pose(bank, k)
        sl = bank.points(k)
        p_cam = pose.apply(bank.p_obj[sl].astype(np.float64))
        xy = p_cam[:, :2] / p_cam[:, 2:]
        err_px = np.abs(xy - bank.xy_n[sl]).max() * intr.fx
        assert err_px < BACKPROJECT_PX


def test_template_border_scales_with_render_px(sprayer_bank):
    bank, _ = sprayer_bank
    k = int(np.argmin(np.abs(bank.view_params_deg[:, 0])))  # tilt 0: side view, axis along image v
    xy = bank.xy_n[bank.points(k)]
    f, _ = template_camera(bank)
    height_px = (xy[:, 1].max() - xy[:, 1].min()) * f.fx
    # 200 mm tall at ~600 mm: about render_px * 200 / diameter pixels (perspective makes it a bit more).
    expected = bank.grid["render_px"] * 200.0 / bank.diameter_mm
    assert expected < height_px < expected * 1.1


def test_bank_round_trip_through_savez(sprayer_bank):
    bank, _ = sprayer_bank
    buf = io.BytesIO()
    np.savez(buf, **bank.to_arrays())
    buf.seek(0)
    back = TemplateBank.from_arrays(np.load(buf))
    for name, value in bank.to_arrays().items():
        np.testing.assert_array_equal(back.to_arrays()[name], value, err_msg=name)
    assert back.grid == bank.grid
    assert back.reference_distance_mm == bank.reference_distance_mm and back.diameter_mm == bank.diameter_mm
    assert buf.getbuffer().nbytes < 20e6


def test_nonsymmetric_grid_covers_the_sphere():
    g = merge_grid({"view_step_deg": 20.0})
    R, params = grid_rotations(g, None)
    assert len(R) == round(4 * np.pi / np.radians(20.0) ** 2)
    eye = np.broadcast_to(np.eye(3), R.shape)
    np.testing.assert_allclose(np.einsum("nij,nkj->nik", R, R), eye, atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(R), 1.0)
    d = fibonacci_directions(len(R))
    # The camera looks along -d: the object centre is straight ahead.
    np.testing.assert_allclose(R[:, 2, :], -d, atol=1e-12)
    az, el = np.radians(params[:, 0]), np.radians(params[:, 1])
    np.testing.assert_allclose(np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)], 1), d,
                               atol=1e-9)
    # Every direction of a fine test set is within ~view_step of a grid direction.
    test = fibonacci_directions(2000)
    nearest = np.degrees(np.arccos(np.clip((test @ d.T).max(axis=1), -1, 1)))
    assert nearest.max() < 20.0


def test_look_from_keeps_object_z_up():
    for d in (np.array([1.0, 0.0, 0.0]), np.array([0.3, -0.8, 0.2]), np.array([0.0, 0.0, 1.0])):
        d = d / np.linalg.norm(d)
        R = look_from_R(d)
        assert rotation_angle_deg(R @ R.T, np.eye(3)) < 1e-6 and np.linalg.det(R) > 0
        if abs(d[2]) < 0.99:
            up_cam = R @ np.array([0.0, 0.0, 1.0])
            assert up_cam[1] < 0 and abs(up_cam[0]) < 1e-12  # up in the image, no roll


def test_symmetric_grid_follows_a_given_axis(sprayer_mesh):
    # The same part with its axis along x: R_tpl_obj @ axis is the tilted +y, as with the +y part.
    A = R_from_rotvec(np.radians(90.0) * np.array([0.0, 0.0, 1.0]))  # y -> -x
    mesh = sprayer_mesh.copy()
    mesh.vertices = mesh.vertices @ A.T
    bank = build_bank(mesh, symmetry="x", grid={"tilt_step_deg": 45.0, "render_px": 100})
    for k, t in enumerate(bank.view_params_deg[:, 0]):
        a = bank.R_tpl_obj[k] @ bank.symmetry_axis_obj
        np.testing.assert_allclose(a, Rx(t) @ [0.0, 1.0, 0.0], atol=1e-9)


@pytest.mark.parametrize(
    "grid",
    [
        {"tilt_stepdeg": 2.0},
        {"tilt_step_deg": 0.0},
        {"tilt_step_deg": -5},
        {"tilt_step_deg": "2"},
        {"tilt_step_deg": True},
        {"tilt_step_deg": float("nan")},
        {"tilt_range_deg": [10.0, -10.0]},
        {"tilt_range_deg": [-200.0, 0.0]},
        {"tilt_range_deg": 5.0},
        {"render_px": 10.5},
        {"render_px": 100000},
        {"spacing_px": 0},
        {"supersample": 3.5},
        {"view_step_deg": 0.5},
        {"reference_distance_mm": 50.0},  # closer than the part is large
    ],
)
def test_bad_grid_options_raise_value_error(sprayer_mesh, grid):
    with pytest.raises(ValueError) as e:
        build_bank(sprayer_mesh, symmetry="y", grid=grid)
    msg = str(e.value)
    assert msg.endswith(".") and "\n" not in msg


def test_bad_symmetry_option_raises_value_error(sprayer_mesh):
    with pytest.raises(ValueError):
        build_bank(sprayer_mesh, symmetry="w")


def test_merge_grid_keeps_defaults_and_types():
    g = merge_grid({"render_px": 200.0, "tilt_range_deg": (-30, 30)})
    assert g["render_px"] == 200 and isinstance(g["render_px"], int)
    assert g["tilt_range_deg"] == [-30.0, 30.0]
    assert g["spacing_px"] == GRID_DEFAULTS["spacing_px"]
    assert merge_grid(None) == merge_grid({})


def test_draw_template_shows_mesh_and_border(sprayer_bank):
    from service.vision.model.templates import draw_template

    bank, _ = sprayer_bank
    intr, (w, h) = template_camera(bank)
    k = bank.n_templates // 2
    img = draw_template(bank, k)
    assert img.dtype == np.uint8 and img.ndim == 3 and img.shape[2] == 3
    assert img.shape[1] == 2 * w + 4 and img.shape[0] > h
    body = img[img.shape[0] - h:]
    left, right = body[:, :w], body[:, w + 4:]
    assert (left.max(axis=2) > 100).sum() > 1000  # the shaded mesh
    uv = np.rint(bank.xy_n[bank.points(k)] * intr.fx + [intr.cx, intr.cy]).astype(int)
    assert (right[uv[:, 1], uv[:, 0]].max(axis=1) > 100).mean() > 0.9  # the border is drawn where it is
    with pytest.raises(IndexError):
        draw_template(bank, bank.n_templates)


def _segment_distance(p, a, b):
    """(N,) distance of points p to the nearest of the segments a[i] -> b[i]."""
    ab = b - a
    t = ((p[:, None, :] - a[None]) * ab[None]).sum(-1) / np.maximum((ab**2).sum(-1), 1e-12)[None]
    t = np.clip(t, 0.0, 1.0)
    q = a[None] + t[..., None] * ab[None]
    return np.linalg.norm(p[:, None, :] - q, axis=2).min(axis=1)


@pytest.mark.parametrize(
    "case", ["x10", "x45", "x90", "z-30", "z30"],  # the paper's Tables I and III
)
def test_paper_scanline_border_matches_contour_border(sprayer_mesh, case):
    from service.vision.geometry.frames import Rz
    from service.vision.reference.scanline import scanline_border

    K = np.array([[1100.0, 0.0, 643.0], [0.0, 1100.0, 477.0], [0.0, 0.0, 1.0]])
    angle = float(case[1:])
    R = Rx(angle) if case[0] == "x" else Rz(angle) @ Rx(10.0)
    pose = Pose(R, np.array([0.0, 0.0, 500.0]) - R @ np.array([0.0, 100.0, 0.0]))  # the paper's tz = 500
    scan = scanline_border(sprayer_mesh.vertices, sprayer_mesh.faces, pose, K)
    uv, _, _ = border_at_pose(sprayer_mesh.vertices, sprayer_mesh.faces, pose, K, (1280, 960), supersample=4)
    assert len(scan) > 100
    # Every scan-line border node lies on the contour-method border ...
    nxt = np.roll(uv, -1, axis=0)
    close = np.linalg.norm(nxt - uv, axis=1) < 3.0
    assert _segment_distance(scan, uv[close], nxt[close]).max() < SCANLINE_ON_CONTOUR_PX
    # ... and the scan-line border (the line built through its nodes) covers every contour point.
    assert _segment_distance(uv, scan, np.roll(scan, -1, axis=0)).max() < SCANLINE_COVERS_CONTOUR_PX


def _topology_brute_force(V, F):
    """(closed, {undirected edge: sorted face pair}) by counting directed edges in a dict."""
    directed: dict[tuple[int, int], list[int]] = {}
    for f, tri in enumerate(np.asarray(F).tolist()):
        for a, b in ((tri[0], tri[1]), (tri[1], tri[2]), (tri[2], tri[0])):
            directed.setdefault((a, b), []).append(f)
    closed = all(a != b and len(fs) == 1 and len(directed.get((b, a), [])) == 1
                 for (a, b), fs in directed.items())
    if closed:
        closed = trimesh.Trimesh(V, F, process=False).volume > 0
    pairs = {(min(a, b), max(a, b)): tuple(sorted(directed[(a, b)] + directed[(b, a)]))
             for (a, b) in directed if a < b} if closed else {}
    return closed, pairs


def test_mesh_topology_matches_brute_force():
    from service.vision.geometry.silhouette import _build_topology, is_closed_outward

    rng = np.random.default_rng(19)
    sph = trimesh.creation.icosphere(subdivisions=2, radius=50.0)
    box = trimesh.creation.box((10.0, 20.0, 30.0))
    flipped = sph.faces.copy()
    flipped[7] = flipped[7, ::-1]  # one face wound the other way
    perm = rng.permutation(len(sph.faces))
    cases = {"sphere": (sph.vertices, sph.faces), "box": (box.vertices, box.faces),
             "shuffled": (sph.vertices, sph.faces[perm][:, [1, 2, 0]]),
             "inward": (sph.vertices, sph.faces[:, ::-1]), "open": (sph.vertices, sph.faces[1:]),
             "flipped": (sph.vertices, flipped), "doubled": (sph.vertices, np.vstack([sph.faces, sph.faces])),
             "degenerate": (sph.vertices, np.vstack([sph.faces, [[0, 0, 1]]]))}
    expect_closed = {"sphere": True, "box": True, "shuffled": True, "inward": False, "open": False,
                     "flipped": False, "doubled": False, "degenerate": False}
    for name, (V, F) in cases.items():
        closed, pairs = _topology_brute_force(V, F)
        assert closed == expect_closed[name], name
        topo = _build_topology(np.asarray(V, float), np.asarray(F, np.int32))
        assert topo.closed == closed == is_closed_outward(V, F), name
        got = {tuple(e): tuple(sorted(fs)) for e, fs in zip(topo.edges.tolist(), topo.edge_faces.tolist(),
                                                             strict=True)}
        assert got == pairs and len(topo.edges) == len(pairs), name
