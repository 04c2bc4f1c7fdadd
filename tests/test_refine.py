"""Pose refinement: known answers on synthetic renders, never-worse, occlusion, lens distortion,
residuals and Jacobian against finite differences, and a real render of the paper set."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from service.vision.estimate.chamfer import sample, sample_with_grad, segment_distance_tensor
from service.vision.estimate.edges import Segments, detect_segments
from service.vision.estimate.refine import (
    _project_jac,
    border_points,
    dt_residuals,
    line_residuals,
    match_lines,
    project_border,
    refine_pose,
)
from service.vision.geometry.camera import Intrinsics
from service.vision.geometry.frames import Pose, R_from_rotvec, canonical_spin, rotation_angle_deg
from service.vision.geometry.render import render, render_shaded
from service.vision.geometry.rotations import PoseParams
from service.vision.geometry.silhouette import Border
from tests.lens import distort_image
from tests.tolerances import (
    REFINE_ANGLE_DEG,
    REFINE_COMPILED_ATOL,
    REFINE_DEPTH_MM,
    REFINE_FREE_ANGLE_DEG,
    REFINE_JAC_ROWS,
    REFINE_JAC_RTOL,
    REFINE_OCCLUDED_ANGLE_DEG,
    REFINE_OCCLUDED_TRANS_MM,
    REFINE_REAL_AXIS_DEG,
    REFINE_REAL_TRANS_MM,
    REFINE_SAMPLE_ATOL,
    REFINE_SEGMENT_DT_ATOL,
    REFINE_TRANS_MM,
    ROUND_TRIP_ATOL,
)

INTR = Intrinsics(fx=1100.0, fy=1100.0, cx=643.0, cy=477.0)
SIZE = (1280, 960)
TLESS_POSE = Pose.from_euler_xyz_deg((25.0, -35.0, 15.0), (40.0, -30.0, 500.0))
SPRAYER_POSE = Pose.from_euler_xyz_deg((-40.0, 25.0, 60.0), (60.0, -40.0, 500.0))
TINY_GRID = {"render_px": 100, "supersample": 1}


@pytest.fixture(scope="module")
def tless_bank(tless06_mesh):
    from service.vision.model.templates import build_bank

    return build_bank(tless06_mesh, symmetry="none", grid={**TINY_GRID, "view_step_deg": 60.0})


@pytest.fixture(scope="module")
def sprayer_bank(sprayer_mesh):
    from service.vision.model.templates import build_bank

    return build_bank(sprayer_mesh, symmetry="auto", grid={**TINY_GRID, "tilt_step_deg": 30.0})


def synthetic(bank, pose, *, seed=0, intr=INTR, size=SIZE):
    """Shaded render with mild blur and sensor noise, (h, w) uint8."""
    img = render_shaded(bank.vertices_mm, bank.faces, pose, intr, size).astype(np.float64)
    img = cv2.GaussianBlur(img, (0, 0), 0.6) + np.random.default_rng(seed).normal(0.0, 2.0, img.shape)
    return np.clip(np.rint(img), 0, 255).astype(np.uint8)


def perturb(pose, rng, deg, mm, *, keep_z=False):
    ax = rng.normal(size=3)
    dv = rng.normal(size=3)
    if keep_z:
        dv[2] = 0.0
    R = R_from_rotvec(np.deg2rad(deg) * ax / np.linalg.norm(ax)) @ pose.R
    return Pose(R, pose.t_mm + mm * dv / np.linalg.norm(dv))


def axis_error_deg(bank, a: Pose, b: Pose) -> float:
    ax = bank.symmetry_axis_obj
    return float(np.degrees(np.arccos(np.clip((a.R @ ax) @ (b.R @ ax), -1.0, 1.0))))


def symmetric_translation_error_mm(bank, a: Pose, b: Pose) -> np.ndarray:
    """Error of the axis point (spin-invariant)."""
    q = bank.symmetry_point_obj
    return np.abs(a.apply(q[None])[0] - b.apply(q[None])[0])


# --- building blocks ----------------------------------------------------------------------------


def test_sample_with_grad_values_equal_chamfer_sample_and_grads_equal_differences(tless_bank):
    img = synthetic(tless_bank, TLESS_POSE)
    seg = detect_segments(img, scale=1.0)
    dtt = segment_distance_tensor(seg, (500, 350, 300, 260), n_channels=16)
    rng = np.random.default_rng(1)
    g = rng.uniform([1, 1], [298, 258], (400, 2))
    th = rng.uniform(0, np.pi, 400)
    val, gu, gv, gth = sample_with_grad(dtt, g, th)
    np.testing.assert_allclose(val, sample(dtt, g, th), atol=REFINE_SAMPLE_ATOL)
    # Away from cell boundaries the read-out is smooth: central differences agree.
    h = 1e-4
    fu = (sample(dtt, g + [h, 0], th) - sample(dtt, g - [h, 0], th)) / (2 * h)
    fv = (sample(dtt, g + [0, h], th) - sample(dtt, g - [0, h], th)) / (2 * h)
    ft = (sample(dtt, g, th + h) - sample(dtt, g, th - h)) / (2 * h)
    frac = (g - np.floor(g))
    cf = th * 16 / np.pi
    ok = (np.minimum(frac, 1 - frac).min(1) > 1e-3) & (np.abs(cf - np.rint(cf)) > 1e-3)
    np.testing.assert_allclose(gu[ok], fu[ok], atol=1e-3)
    np.testing.assert_allclose(gv[ok], fv[ok], atol=1e-3)
    np.testing.assert_allclose(gth[ok], ft[ok], atol=1e-2)


def test_segment_distance_tensor_is_the_exact_directional_chamfer_distance():
    rng = np.random.default_rng(2)
    p0 = rng.uniform(0, 40, (9, 2)).astype(np.float32)
    p1 = (p0 + rng.uniform(-12, 12, (9, 2))).astype(np.float32)
    d = p1 - p0
    th = np.mod(np.arctan2(d[:, 1], d[:, 0]), np.pi).astype(np.float32)
    C, tau, lam = 8, 9.0, 1.3
    dtt = segment_distance_tensor(Segments(p0, p1, th, (50, 50)), (0, 0, 45, 41), n_channels=C, tau_px=tau,
                                  lambda_px=lam)
    vv, uu = np.mgrid[0:41, 0:45]
    q = np.stack([uu.ravel(), vv.ravel()], 1).astype(np.float64)
    a, b = p0.astype(np.float64), p1.astype(np.float64)
    t = np.clip(((q[:, None] - a) * (b - a)).sum(2) / ((b - a) ** 2).sum(1), 0, 1)
    dist = np.linalg.norm(q[:, None] - (a + t[..., None] * (b - a)), axis=2)  # (P, S)
    ch = np.mod(np.floor(th * C / np.pi + 0.5), C).astype(int)
    for c in range(C):
        cyc = np.minimum(np.abs(ch - c), C - np.abs(ch - c))
        brute = np.minimum((dist + lam * cyc).min(1), tau).reshape(41, 45)
        np.testing.assert_allclose(dtt.dt[c], brute, atol=REFINE_SEGMENT_DT_ATOL)


def _jac_agrees(fun, x, n):
    r, J = fun(x)
    h = 1e-6
    Jn = np.empty_like(J)
    for k in range(n):
        e = np.zeros(n)
        e[k] = h
        Jn[:, k] = (fun(x + e)[0] - fun(x - e)[0]) / (2 * h)
    scale = np.maximum(np.abs(Jn).max(0), 1e-9)
    ok = np.all(np.abs(J - Jn) <= REFINE_JAC_RTOL * scale + 1e-6, axis=1)
    return ok.mean()


# A plane's normal (camera frame) for the parametrisation on a plane: any unit vector serves the algebra.
PLANE_NORMAL_CAM = np.array([0.2, -0.6, -0.77]) / np.linalg.norm([0.2, -0.6, -0.77])
KINDS = ["free", "held_distance", "symmetric", "on_plane", "symmetric_on_plane",
         "symmetric_standing_on_plane"]


def params_of(kind: str, bank, start: Pose) -> PoseParams:
    """The parametrisation a refinement of ``kind`` moves ``start`` in (standing: the plane's normal along
    the revolved part's axis)."""
    normal = PLANE_NORMAL_CAM if kind.endswith("on_plane") else None
    if "standing" in kind:
        normal = start.R @ np.asarray(bank.symmetry_axis_obj, float)
        normal /= np.linalg.norm(normal)
    return PoseParams(start, bank.centre_obj, bank.symmetry_axis_obj,
                      float(start.t_mm[2]) if kind == "held_distance" else None, normal)


@pytest.mark.parametrize("kind", KINDS)
def test_residuals_and_jacobian_agree_with_finite_differences(kind, tless_bank, sprayer_bank):
    bank, pose = (sprayer_bank, SPRAYER_POSE) if kind.startswith("symmetric") else (tless_bank, TLESS_POSE)
    img = synthetic(bank, pose)
    start = perturb(pose, np.random.default_rng(5), 2.0, 3.0)
    border = border_points(bank, start, INTR, SIZE)
    seg = detect_segments(img, scale=1.0)
    dtt = segment_distance_tensor(seg, (0, 0, SIZE[0], SIZE[1]), n_channels=16)
    params = params_of(kind, bank, start)
    x = np.random.default_rng(6).normal(0.0, 1.0, params.n) * np.r_[np.full(params.nr, 0.01), np.ones(
        params.n - params.nr)]
    if kind == "held_distance":
        assert params.pose(x).t_mm[2] == pytest.approx(start.t_mm[2], abs=1e-9)
    if kind.endswith("on_plane"):  # spun about the normal and slid along the plane: no point's height moves
        # (a revolved part standing on its axis has no spin left to refine)
        assert params.n == params.nr + 2 and params.nr == (0 if "standing" in kind else 1)
        normal = np.cross(params.T[:, 0], params.T[:, 1])  # the plane's, up to its sign
        np.testing.assert_allclose(params.pose(x).apply(bank.vertices_mm) @ normal,
                                   start.apply(bank.vertices_mm) @ normal, atol=ROUND_TRIP_ATOL)
    assert _jac_agrees(lambda x: dt_residuals(params, x, border, INTR, dtt), x, params.n) >= REFINE_JAC_ROWS
    uv, th, _, _ = project_border(params, x, border, INTR, with_jac=False)
    match = match_lines(uv, th, seg, gate_px=10.0)
    assert len(match.idx) > 20
    r, J = line_residuals(params, x, border, INTR, match)
    assert _jac_agrees(lambda x: line_residuals(params, x, border, INTR, match), x, params.n) == 1.0
    # The DT residual is the chamfer read-out of the projected border (its definition).
    r_dt, _ = dt_residuals(params, x, border, INTR, dtt, with_jac=False)
    np.testing.assert_allclose(r_dt, sample(dtt, dtt.to_grid(uv), th), atol=REFINE_SAMPLE_ATOL)


def test_border_orientation_follows_the_projected_3d_tangent(tless_bank):
    b = border_points(tless_bank, TLESS_POSE, INTR, SIZE)
    params = PoseParams(TLESS_POSE, tless_bank.centre_obj)
    uv, th, _, _ = project_border(params, np.zeros(params.n), b, INTR, with_jac=False)
    d = np.roll(uv, -1, 0) - np.roll(uv, 1, 0)
    th_chain = np.mod(np.arctan2(d[:, 1], d[:, 0]), np.pi)
    diff = np.abs(np.angle(np.exp(2j * (th - th_chain)))) / 2
    assert np.median(np.degrees(diff)) < 5.0


# --- known answers ------------------------------------------------------------------------------


@pytest.mark.parametrize("seed", [0, 1])
def test_perturbed_pose_converges_back_non_symmetric(seed, tless_bank):
    img = synthetic(tless_bank, TLESS_POSE, seed=seed)
    start = perturb(TLESS_POSE, np.random.default_rng(10 + seed), 3.0, 5.0, keep_z=True)
    res = refine_pose(tless_bank, start, img, INTR, distance_mm=float(TLESS_POSE.t_mm[2]))
    assert res.converged
    assert rotation_angle_deg(res.pose.R, TLESS_POSE.R) <= REFINE_ANGLE_DEG
    assert np.abs(res.pose.t_mm - TLESS_POSE.t_mm).max() <= REFINE_TRANS_MM
    assert res.score > 0.9 and 0.0 < res.inlier_ratio <= 1.0 and res.iterations > 0 and res.cost < 1.0


def test_perturbed_pose_converges_back_with_distance_refined(tless_bank):
    img = synthetic(tless_bank, TLESS_POSE, seed=3)
    start = perturb(TLESS_POSE, np.random.default_rng(13), 3.0, 5.0)
    res = refine_pose(tless_bank, start, img, INTR)
    assert rotation_angle_deg(res.pose.R, TLESS_POSE.R) <= REFINE_FREE_ANGLE_DEG
    assert np.abs(res.pose.t_mm[:2] - TLESS_POSE.t_mm[:2]).max() <= REFINE_TRANS_MM
    assert abs(res.pose.t_mm[2] - TLESS_POSE.t_mm[2]) <= REFINE_DEPTH_MM


@pytest.mark.xfail(reason=(
    "edge bias, not the solver: at the true pose LSD puts one side's outline 0.2-0.4 px inside the "
    "silhouette (the shading ramps towards the limb there) and the other side's at 0.0, so the fit "
    "tilts the axis by 0.14-0.2 deg against the 0.1 deg tolerance (T-LESS 6 and the paper renders pass)"))
def test_symmetric_part_converges_back_and_reports_the_canonical_spin(sprayer_bank):
    img = synthetic(sprayer_bank, SPRAYER_POSE)
    start = perturb(SPRAYER_POSE, np.random.default_rng(20), 3.0, 5.0, keep_z=True)
    res = refine_pose(sprayer_bank, start, img, INTR, distance_mm=float(SPRAYER_POSE.t_mm[2]))
    assert axis_error_deg(sprayer_bank, res.pose, SPRAYER_POSE) <= REFINE_ANGLE_DEG
    assert symmetric_translation_error_mm(sprayer_bank, res.pose, SPRAYER_POSE).max() <= REFINE_TRANS_MM
    np.testing.assert_allclose(res.pose.R, canonical_spin(res.pose, sprayer_bank.symmetry_axis_obj).R,
                               atol=1e-9)
    # The held distance is the object origin's camera z, also after the spin is canonicalised.
    assert res.pose.t_mm[2] == pytest.approx(SPRAYER_POSE.t_mm[2], abs=1e-6)


def test_paper_eq18_median_threshold_option_also_converges(tless_bank):
    img = synthetic(tless_bank, TLESS_POSE, seed=4)
    start = perturb(TLESS_POSE, np.random.default_rng(14), 2.0, 3.0, keep_z=True)
    res = refine_pose(tless_bank, start, img, INTR, distance_mm=float(TLESS_POSE.t_mm[2]), loss="median")
    assert rotation_angle_deg(res.pose.R, TLESS_POSE.R) <= 2 * REFINE_ANGLE_DEG
    assert np.abs(res.pose.t_mm - TLESS_POSE.t_mm).max() <= 2 * REFINE_TRANS_MM


def test_refined_pose_is_never_worse_than_the_start_on_a_seeded_batch(tless_bank):
    from service.vision.estimate.refine import SCORE_SLACK, verify

    img = synthetic(tless_bank, TLESS_POSE, seed=7)
    dtt = segment_distance_tensor(detect_segments(img, scale=1.0), (0, 0, SIZE[0], SIZE[1]))
    rng = np.random.default_rng(30)
    for k in range(8):
        # Coarse-like errors (pose error must not grow) and far-off starts (the score must not drop).
        deg, mm = (2.0, 4.0) if k < 5 else (10.0, 25.0)
        start = perturb(TLESS_POSE, rng, deg, mm, keep_z=True)
        res = refine_pose(tless_bank, start, img, INTR, distance_mm=500.0)
        score0, _, _ = verify(border_points(tless_bank, start, INTR, SIZE), start, INTR, dtt, score_px=3.0)
        # the same read-out (here on a whole-image DT: rounding) with the refinement's SCORE_SLACK
        assert res.score >= score0 - 0.02 - SCORE_SLACK
        if not res.converged:
            np.testing.assert_allclose(res.pose.R, start.R)
        if k < 5:
            assert rotation_angle_deg(res.pose.R, TLESS_POSE.R) <= rotation_angle_deg(start.R, TLESS_POSE.R)
            err0 = np.linalg.norm(start.t_mm - TLESS_POSE.t_mm)
            assert np.linalg.norm(res.pose.t_mm - TLESS_POSE.t_mm) <= err0


def test_occluded_target_still_refines(tless_bank):
    img = synthetic(tless_bank, TLESS_POSE, seed=8)
    mask = render(tless_bank.vertices_mm, tless_bank.faces, TLESS_POSE, INTR, SIZE).mask
    vs, us = np.nonzero(mask)
    # A textured background-like patch over the right 30 % of the silhouette's area.
    u_cut = np.quantile(us, 0.70)
    rng = np.random.default_rng(9)
    patch = rng.normal(70, 8, img.shape)
    hide = np.zeros_like(mask)
    hide[vs.min() - 20:vs.max() + 20, int(u_cut):us.max() + 20] = True
    occluded = np.where(hide, np.clip(patch, 0, 255), img).astype(np.uint8)
    assert (mask & hide).sum() >= 0.3 * mask.sum() - 1
    start = perturb(TLESS_POSE, np.random.default_rng(40), 2.0, 3.0, keep_z=True)
    res = refine_pose(tless_bank, start, occluded, INTR, distance_mm=500.0)
    assert rotation_angle_deg(res.pose.R, TLESS_POSE.R) <= REFINE_OCCLUDED_ANGLE_DEG
    assert np.abs(res.pose.t_mm - TLESS_POSE.t_mm).max() <= REFINE_OCCLUDED_TRANS_MM
    assert res.inlier_ratio < 0.9  # the hidden part is recognised as outliers


def test_lens_distortion_k1_minus_0_2_recovers_the_pose_as_well(tless_bank):
    intr_d = Intrinsics(INTR.fx, INTR.fy, INTR.cx, INTR.cy, (-0.2, 0.0, 0.0, 0.0))
    # Render at twice the resolution, then distort and reduce (anti-aliased like the others).
    pose = Pose(TLESS_POSE.R, np.array([170.0, 110.0, 500.0]))  # off-centre: distortion ~10 px here
    big = synthetic(tless_bank, pose, intr=INTR.scaled(2), size=(2 * SIZE[0], 2 * SIZE[1]))
    img = distort_image(big, Intrinsics(*[getattr(INTR.scaled(2), k) for k in ("fx", "fy", "cx", "cy")],
                                         intr_d.dist))
    img = cv2.resize(img, SIZE, interpolation=cv2.INTER_AREA)
    start = perturb(pose, np.random.default_rng(50), 3.0, 5.0, keep_z=True)
    res = refine_pose(tless_bank, start, img, intr_d, distance_mm=500.0)
    assert rotation_angle_deg(res.pose.R, pose.R) <= REFINE_ANGLE_DEG
    assert np.abs(res.pose.t_mm - pose.t_mm).max() <= REFINE_TRANS_MM
    # Ignoring the distortion would be visibly wrong (the check above is not vacuous).
    bad = refine_pose(tless_bank, start, img, INTR, distance_mm=500.0)
    assert np.abs(bad.pose.t_mm - pose.t_mm).max() > 2 * REFINE_TRANS_MM


def test_far_off_start_keeps_the_start_pose(tless_bank):
    img = np.full((SIZE[1], SIZE[0]), 70, np.uint8)  # nothing to refine against
    start = perturb(TLESS_POSE, np.random.default_rng(60), 1.0, 1.0, keep_z=True)
    res = refine_pose(tless_bank, start, img, INTR, distance_mm=500.0)
    assert not res.converged and res.score == 0.0
    np.testing.assert_allclose(res.pose.R, start.R)
    np.testing.assert_allclose(res.pose.t_mm, start.t_mm)


def test_bad_options_raise(tless_bank):
    img = synthetic(tless_bank, TLESS_POSE)
    with pytest.raises(ValueError):
        refine_pose(tless_bank, TLESS_POSE, img, INTR, loss="l2")
    with pytest.raises(ValueError):
        refine_pose(tless_bank, TLESS_POSE, img, INTR, residual="icp")


def test_border_type_is_the_documented_one(tless_bank):
    b = border_points(tless_bank, TLESS_POSE, INTR, SIZE)
    assert isinstance(b, Border) and b.p_obj.shape == b.tan_obj.shape and b.p_obj.shape[1] == 3
    np.testing.assert_allclose(np.linalg.norm(b.tan_obj, axis=1), 1.0, atol=1e-9)


def _dt_residuals_numpy(params, x, border, intr, dtt, with_jac):
    """The "dt" residual in numpy steps: the border projected, the chamfer read-out, its chain rule."""
    uv, theta, duv, dth = project_border(params, x, border, intr, with_jac)
    val, gu, gv, gth = sample_with_grad(dtt, dtt.to_grid(uv), theta)
    if not with_jac:
        return val / dtt.scale, None
    J = gu[:, None] * duv[:, 0] + gv[:, None] * duv[:, 1] + (gth / dtt.scale)[:, None] * dth
    return val / dtt.scale, J


def _line_residuals_numpy(params, x, border, intr, match, with_jac):
    pc, Jp = params.points(x, border.p_obj[match.idx], with_jac)
    uv, duv = _project_jac(pc, intr, Jp)
    r = (match.normal * uv).sum(1) - match.offset
    if not with_jac:
        return r, None
    return r, match.normal[:, 0, None] * duv[:, 0] + match.normal[:, 1, None] * duv[:, 1]


@pytest.mark.parametrize("kind", KINDS)
def test_compiled_residuals_equal_their_numpy_steps(kind, tless_bank, sprayer_bank):
    bank, pose = (sprayer_bank, SPRAYER_POSE) if kind.startswith("symmetric") else (tless_bank, TLESS_POSE)
    img = synthetic(bank, pose)
    start = perturb(pose, np.random.default_rng(8), 2.0, 3.0)
    border = border_points(bank, start, INTR, SIZE)
    seg = detect_segments(img, scale=1.0)
    # A window smaller than the border's reach: some points read outside the grid (tau, zero gradient).
    dtt = segment_distance_tensor(seg, (500, 300, 200, 250), n_channels=16)
    params = params_of(kind, bank, start)
    x = np.random.default_rng(9).normal(0.0, 1.0, params.n) * np.r_[np.full(params.nr, 0.01), np.ones(
        params.n - params.nr)]
    uv, th, _, _ = project_border(params, x, border, INTR, with_jac=False)
    match = match_lines(uv, th, seg, gate_px=10.0)
    assert len(match.idx) > 20
    for with_jac in (True, False):
        r, J = dt_residuals(params, x, border, INTR, dtt, with_jac)
        r0, J0 = _dt_residuals_numpy(params, x, border, INTR, dtt, with_jac)
        assert np.any(r0 == dtt.tau_px / dtt.scale) and np.any(r0 < dtt.tau_px / dtt.scale)
        np.testing.assert_allclose(r, r0, rtol=0, atol=REFINE_COMPILED_ATOL)
        r, Jl = line_residuals(params, x, border, INTR, match, with_jac)
        r0, Jl0 = _line_residuals_numpy(params, x, border, INTR, match, with_jac)
        np.testing.assert_allclose(r, r0, rtol=0, atol=REFINE_COMPILED_ATOL)
        if with_jac:
            np.testing.assert_allclose(J, J0, rtol=0, atol=REFINE_COMPILED_ATOL)
            np.testing.assert_allclose(Jl, Jl0, rtol=0, atol=REFINE_COMPILED_ATOL)
        else:
            assert J is None and Jl is None


# --- a real render ------------------------------------------------------------------------------


def test_paper_render_0001_from_perturbed_gt(data_dir, sprayer_bank):
    g = json.loads((data_dir / "paper" / "gt.jsonl").read_text().splitlines()[0])
    img = cv2.imread(str(data_dir / "paper" / g["image"]), cv2.IMREAD_GRAYSCALE)
    intr = Intrinsics.from_K(np.array(g["K"]))
    gt = Pose(np.array(g["R"]), np.array(g["t_mm"]))
    start = perturb(gt, np.random.default_rng(70), 1.0, 2.0, keep_z=True)
    res = refine_pose(sprayer_bank, start, img, intr, distance_mm=500.0)
    assert np.abs(res.pose.t_mm[:2] - gt.t_mm[:2]).max() <= REFINE_REAL_TRANS_MM
    assert axis_error_deg(sprayer_bank, res.pose, gt) <= REFINE_REAL_AXIS_DEG


def test_symmetric_result_is_canonical_and_keeps_the_held_distance(sprayer_bank):
    img = synthetic(sprayer_bank, SPRAYER_POSE)
    start = perturb(SPRAYER_POSE, np.random.default_rng(21), 1.0, 2.0, keep_z=True)
    res = refine_pose(sprayer_bank, start, img, INTR, distance_mm=float(SPRAYER_POSE.t_mm[2]))
    np.testing.assert_allclose(res.pose.R, canonical_spin(res.pose, sprayer_bank.symmetry_axis_obj).R,
                               atol=1e-9)
    assert res.pose.t_mm[2] == pytest.approx(SPRAYER_POSE.t_mm[2], abs=1e-6)
    # The translation stays consistent with the spin removed: the axis point is where it was.
    assert symmetric_translation_error_mm(sprayer_bank, res.pose, SPRAYER_POSE).max() <= 1.0


def test_match_lines_is_the_brute_force_nearest_gated_segment():
    """Every border point gets the segment a plain loop over all segments picks: the nearest (endpoints
    extended by 1 px) within the orientation and distance gates, the first one on a tie; the per-point
    box test only skips segments beyond the gate."""
    rng = np.random.default_rng(7)
    p0 = rng.uniform(0, 400, (300, 2)).astype(np.float32)
    p1 = (p0 + rng.normal(0, 15, (300, 2))).astype(np.float32)
    d = p1 - p0
    seg = Segments(p0, p1, np.mod(np.arctan2(d[:, 1], d[:, 0]), np.pi).astype(np.float32), (400, 400))
    # points near the segments (most match) and scattered (most do not), in runs along a walk
    near = p0[rng.integers(0, 300, 500)] + rng.normal(0, 2, (500, 2))
    uv = np.concatenate([near, np.cumsum(rng.normal(0, 3, (400, 2)), axis=0) + 200])
    theta = rng.uniform(0, np.pi, len(uv))
    m = match_lines(uv, theta, seg)
    want = []
    for k, (q, th) in enumerate(zip(uv, theta, strict=True)):
        best, best_j = np.inf, -1
        for j in range(len(seg)):
            a, b = seg.uv0[j].astype(float), seg.uv1[j].astype(float)
            length = max(np.linalg.norm(b - a), 1e-9)
            e = (b - a) / length
            t = np.clip((q - a) @ e, -1.0, length + 1.0)
            dist = np.linalg.norm(q - a - t * e)
            seg_theta = np.mod(np.arctan2(b[1] - a[1], b[0] - a[0]), np.pi)
            if abs(np.cos(th - seg_theta)) >= np.cos(np.radians(20.0)) and dist < best:
                best, best_j = dist, j
        if best <= 3.0:
            want.append((k, best_j))
    assert len(want) > 100
    assert m.idx.tolist() == [k for k, _ in want]
    d_want = np.array([seg.uv1[j] - seg.uv0[j] for _, j in want], float)
    e = d_want / np.linalg.norm(d_want, axis=1, keepdims=True)
    np.testing.assert_allclose(m.normal, np.stack([-e[:, 1], e[:, 0]], 1), atol=1e-12)


def test_interior_later_gives_the_same_refinement(tless_bank):
    img = synthetic(tless_bank, TLESS_POSE, seed=5)
    start = perturb(TLESS_POSE, np.random.default_rng(15), 2.0, 3.0)
    ref = refine_pose(tless_bank, start, img, INTR)
    later = refine_pose(tless_bank, start, img, INTR, interior_later=True)
    assert np.isnan(later.unexplained) and later.unexplained_later() == ref.unexplained
    assert np.array_equal(later.pose.R, ref.pose.R) and np.array_equal(later.pose.t_mm, ref.pose.t_mm)
    assert (later.cost, later.score, later.iterations, later.inlier_ratio) == (
        ref.cost, ref.score, ref.iterations, ref.inlier_ratio)
