"""bench/synth_light.py: realistic shading of the synthetic scenes, checked against geometry."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from bench import synth_light as L  # noqa: N812
from bench import synth_scenes as S  # noqa: N812
from service.vision.geometry.frames import Pose
from service.vision.geometry.render import render

K = np.array([[800.0, 0, 319.5], [0, 800.0, 239.5], [0, 0, 1]])
W, H = 640, 480


def look(**kw) -> L.Look:
    base = dict(ambient=0.4, smooth=True, crease_deg=40.0, specular=0.0, shininess=50.0, shadows=True,
                light_radius_deg=0.0, gamma=2.2, blur_px=0.0, light=(0.0, 0.0, -1.0))
    return L.Look(**(base | kw))


def test_cylinder_corner_normals_are_radial_on_the_side_and_axial_on_the_caps():
    m = trimesh.creation.cylinder(radius=10.0, height=30.0, sections=32)
    V, F = np.asarray(m.vertices), np.asarray(m.faces)
    cn = L.corner_normals(V, F, 40.0)
    fn = np.asarray(m.face_normals)
    cap = np.abs(fn[:, 2]) > 0.99
    assert cap.any() and (~cap).any()
    # caps: every corner keeps the cap's own normal (the 90 deg edge is a crease)
    assert np.allclose(cn[cap], fn[cap][:, None, :], atol=1e-9)
    # side: the corner normal is the radial direction of its vertex (smooth round the cylinder)
    side_v = V[F[~cap]]
    radial = side_v * np.array([1, 1, 0])
    radial /= np.linalg.norm(radial, axis=2, keepdims=True)
    assert np.allclose(np.abs(np.einsum("fkj,fkj->fk", cn[~cap], radial)), 1.0, atol=1e-6)


def test_surface_points_lie_on_their_faces_and_reproduce_their_pixels():
    m = trimesh.creation.icosphere(subdivisions=2, radius=50.0)
    V, F = np.asarray(m.vertices), np.asarray(m.faces, np.int32)
    pose = Pose(np.eye(3), np.array([10.0, -5.0, 600.0]))
    r = render(V, F, pose, K, (W, H), supersample=2)
    mask, P, f, w = L.surface_points(r, V, F, pose)
    tri = (V @ pose.R.T + pose.t_mm)[F[f]]
    # inside its own face (the z-buffer holds float32 depths: a micrometre)
    assert np.allclose(np.einsum("mk,mkj->mj", w, tri), P, atol=1e-3)
    j, i = np.nonzero(mask)
    uv = P @ r.K_ss.T
    assert np.allclose(uv[:, 0] / uv[:, 2], i + r.roi_ss[0], atol=1e-6)
    assert np.allclose(uv[:, 1] / uv[:, 2], j + r.roi_ss[1], atol=1e-6)
    # a smooth sphere's normal is its radius direction (within the facets' error)
    n = L.shading_normals(r, V, F, pose, f, w, look())
    radial = (P - pose.t_mm) / np.linalg.norm(P - pose.t_mm, axis=1, keepdims=True)
    assert np.median(np.einsum("ij,ij->i", n, radial)) > 0.999


def test_specular_highlight_sits_at_the_mirror_direction():
    m = trimesh.creation.icosphere(subdivisions=5, radius=60.0)
    V, F = np.asarray(m.vertices), np.asarray(m.faces, np.int32)
    C = np.array([0.0, 0.0, 700.0])
    pose = Pose(np.eye(3), C)
    light = np.array(L.light_direction(30.0, 0.7))
    lk = look(ambient=0.0, specular=1.0, shininess=400.0, light=tuple(light))
    r = render(V, F, pose, K, (W, H), supersample=1)
    mask, P, f, w = L.surface_points(r, V, F, pose)
    n = L.shading_normals(r, V, F, pose, f, w, lk)
    spec = L.radiance(np.zeros(3), n, P, light, np.ones(len(P)), lk)[:, 0]
    # the mirror point: where the sphere's normal bisects the light and the view (to the camera)
    view = -C / np.linalg.norm(C)
    half = (view + light) / np.linalg.norm(view + light)
    Q = C + 60.0 * half
    q = K @ Q
    j, i = np.nonzero(mask)
    k = int(np.argmax(spec))
    assert np.hypot(i[k] + r.roi_ss[0] - q[0] / q[2], j[k] + r.roi_ss[1] - q[1] / q[2]) < 2.0


@pytest.mark.parametrize("ambient", [0.3, 0.6])
def test_shadowed_floor_is_darker_than_its_lit_twin_by_the_ambient_ratio(ambient):
    # a fronto-parallel floor at 1500 mm, a box at 800 mm on the optical axis, light along the axis
    # tilted 20 deg: its shadow is the box's silhouette moved along the light onto the floor
    light = np.array(L.light_direction(20.0, 0.0))
    lk = look(ambient=ambient, light=tuple(light))
    box = trimesh.creation.box(extents=(100.0, 100.0, 100.0))
    V, F = np.asarray(box.vertices), np.asarray(box.faces, np.int32)
    pose = Pose(np.eye(3), np.array([0.0, 0.0, 800.0]))
    floor_depth = np.full((H, W), 1500.0, np.float32)
    smap = L.ShadowMap([(V, F, pose)], light)
    fac = S.floor_shadow(floor_depth, K, light, lk, smap)
    # where the ray from the box's centre along the light meets the floor
    c = pose.t_mm - light * (1500.0 - 800.0) / -light[2]
    u, v = (K @ c)[:2] / c[2]
    lam = float(np.array([0, 0, -1.0]) @ light)
    want = (ambient / (ambient + (1 - ambient) * lam)) ** (1 / lk.gamma)
    assert fac[int(round(v)), int(round(u))] == pytest.approx(want, abs=1e-3)
    # its twin on the other side of the image is fully lit, and nothing is brighter than lit
    assert fac[int(round(v)), W - 1 - int(round(u))] == pytest.approx(1.0, abs=1e-6)
    assert fac.max() <= 1.0 + 1e-6 and fac.min() >= want - 1e-3


def test_a_convex_part_does_not_shadow_its_lit_faces():
    box = trimesh.creation.box(extents=(80.0, 60.0, 40.0))
    V, F = np.asarray(box.vertices), np.asarray(box.faces, np.int32)
    R = trimesh.transformations.rotation_matrix(0.6, [1, 1, 0])[:3, :3]
    pose = Pose(R, np.array([0.0, 0.0, 500.0]))
    light = np.array(L.light_direction(25.0, 2.0))
    smap = L.ShadowMap([(V, F, pose)], light)
    r = render(V, F, pose, K, (W, H), supersample=2)
    mask, P, f, w = L.surface_points(r, V, F, pose)
    n = L.shading_normals(r, V, F, pose, f, w, look(smooth=False))
    facing = n @ light > 0.2
    assert facing.sum() > 100
    assert (smap.lit(P[facing], n[facing]) == 1.0).mean() > 0.99


def test_real_look_keeps_the_scene_and_its_ground_truth(data_dir):
    models = list(S.DEFAULT_MODELS)
    flat = S.scene(11, 1, 320, 240, models, absent_frac=0.0, clean=True)
    real = S.scene(11, 1, 320, 240, models, absent_frac=0.0, clean=True, look="real")
    for k in ("R", "t_mm", "K", "model", "visible_fraction", "distractors"):
        assert real["gt"][k] == flat["gt"][k]
    assert np.array_equal(real["full_mask"], flat["full_mask"])
    assert not np.array_equal(real["image"], flat["image"])
