"""Region proposals (``vision/estimate/regions.py``): a flat-coloured part on a checker floor is found by
its region, and the proposal's pose is the rendered one."""

import numpy as np
import pytest

from service.vision.estimate import regions, segmentation, shapes
from service.vision.estimate.search import Hypothesis, poses_of
from service.vision.geometry.camera import project
from service.vision.geometry.frames import Pose, Rx, Ry, Rz
from service.vision.geometry.render import rasterise_roi
from service.vision.pipeline import DEFAULT_DISTANCE_RANGE_MM, DEFAULT_POLICY

SEARCH_PARAMS = DEFAULT_POLICY.search_params
K = np.array([[800.0, 0.0, 320.0], [0.0, 800.0, 240.0], [0.0, 0.0, 1.0]])
W, H = 640, 480


def checker_scene(bank, pose: Pose, colour=(40, 150, 210), square_px=24) -> np.ndarray:
    v, u = np.mgrid[0:H, 0:W]
    floor = np.where(((u // square_px) + (v // square_px)) % 2 == 0, 70, 170).astype(np.uint8)
    img = np.repeat(floor[..., None], 3, axis=2)
    _, face, (u0, v0) = rasterise_roi(bank.vertices_mm, bank.faces, pose, K, (W, H))
    win = img[v0:v0 + face.shape[0], u0:u0 + face.shape[1]]
    win[face >= 0] = colour
    return img


def max_vertex_px(bank, a: Pose, b: Pose) -> float:
    """MSPD of a part without symmetry: the largest image distance of any vertex between two poses."""
    V = np.asarray(bank.vertices_mm, float)
    return float(np.linalg.norm(project(a.apply(V), K) - project(b.apply(V), K), axis=1).max())


def template_pose(bank, view: int, phi_deg: float, uv, z_mm: float) -> Pose:
    """The pose a search hypothesis names: template ``view`` turned by ``phi_deg`` about its viewing ray
    through pixel ``uv``, its reference point at depth ``z_mm`` (``coarse.poses_of``)."""
    Rs, ts = poses_of(bank, [Hypothesis(view, phi_deg, z_mm, np.asarray(uv, float))], K, None)
    return Pose(Rs[0], ts[0])


@pytest.mark.parametrize("view, phi_deg, uv, z_mm, tol_px", [
    (40, 25.0, (380.0, 210.0), 650.0, 3.0),  # a template's own view: only the outline's pixels err
    (None, None, None, None, 8.0),  # any rotation: up to half the bank's 15-degree view step
])
def test_a_flat_part_on_a_checker_floor_is_proposed_at_its_pose(l_block_bank, view, phi_deg, uv, z_mm,
                                                                tol_px):
    bank = l_block_bank
    if view is None:
        truth = Pose(Rz(25.0) @ Rx(-40.0) @ Ry(30.0), np.array([60.0, -30.0, 650.0]))
    else:
        truth = template_pose(bank, view, phi_deg, uv, z_mm)
    image = checker_scene(bank, truth)
    props, reg = regions.propose(bank, image, K, DEFAULT_DISTANCE_RANGE_MM, n_out=5)
    assert props
    refined = [regions.refine_on_boundary(bank, r, reg, K, (H, W), SEARCH_PARAMS) for r in props]
    Rs, ts = poses_of(bank, refined, K, None)
    errs = [max_vertex_px(bank, Pose(R, t), truth) for R, t in zip(Rs, ts, strict=True)]
    assert min(errs) < tol_px, errs
    # and the region that proposed it is the part's own: its reference point within a few px of the truth's
    c_uv = project(truth.apply(bank.centre_obj[None]), K)[0]
    best = int(np.argmin(errs))
    assert np.hypot(*(refined[best].uv - c_uv)) < tol_px


# a region's outline refined on: its depth within this of the truth's, the median over several poses
OUTLINE_DEPTH_REL = 0.005


def test_a_region_outline_refines_near_the_rendered_depth(l_block_bank):
    """A flat part on a checker floor at template poses (depths 400-1100 mm): the pose refined on its
    region's outline, through the boundary pixels' centres (a pixel small all round), is found on most
    poses and a little farther than the rendered depth (x 1.023 at the median)."""
    bank = l_block_bank
    rs = np.random.default_rng(0)
    ratios = []
    for _ in range(10):
        truth = template_pose(bank, int(rs.integers(bank.n_templates)), float(rs.uniform(0, 360)),
                              (float(rs.uniform(200, 440)), float(rs.uniform(150, 330))),
                              float(rs.uniform(400, 1100)))
        props, reg = regions.propose(bank, checker_scene(bank, truth), K, DEFAULT_DISTANCE_RANGE_MM, n_out=5)
        refined = [regions.refine_on_boundary(bank, r, reg, K, (H, W), SEARCH_PARAMS) for r in props]
        Rs, ts = poses_of(bank, refined, K, None)
        errs = [max_vertex_px(bank, Pose(R, t), truth) for R, t in zip(Rs, ts, strict=True)]
        z_true = float(truth.t_mm[2] + (truth.R @ bank.centre_obj)[2])  # the reference point's depth
        if errs and min(errs) < 3.0:
            ratios.append(refined[int(np.argmin(errs))].z_mm / z_true)
    assert len(ratios) >= 7
    assert 1.0 + 2 * OUTLINE_DEPTH_REL < np.median(ratios) < 1.05, ratios


def test_region_proposals_give_the_distance_they_were_asked_for(l_block_bank):
    bank = l_block_bank
    truth = template_pose(bank, 100, -60.0, (250.0, 280.0), 700.0)
    image = checker_scene(bank, truth, colour=(200, 60, 60))
    z_true = float(truth.t_mm[2])  # a given distance is the model origin's depth (``poses_of``)
    hs = regions.region_proposals(bank, image, K, (H, W), SEARCH_PARAMS, distance_mm=z_true,
                                  distance_range_mm=DEFAULT_DISTANCE_RANGE_MM, n_out=5)
    Rs, ts = poses_of(bank, hs, K, z_true)
    errs = [max_vertex_px(bank, Pose(R, t), truth) for R, t in zip(Rs, ts, strict=True)]
    assert min(errs) < 3.0, errs


def test_merging_keeps_a_two_tone_part_as_one_region_before_it_meets_the_floor():
    # a square of two close tones (a lit and a shaded face) on a contrasting floor: some region of the
    # hierarchy is exactly the square
    img = np.full((240, 320, 3), 30, np.uint8)
    img[80:160, 100:140] = (150, 150, 150)
    img[80:160, 140:180] = (135, 135, 135)
    reg = segmentation.segment(img, work_width=320)
    target = np.zeros((240, 320), bool)
    target[80:160, 100:180] = True
    assert best_node_iou(reg, target) > 0.97


def best_node_iou(reg, target: np.ndarray) -> float:
    """The highest IoU of any node of the hierarchy with ``target`` (working px)."""
    best = 0.0
    for c in range(len(reg.children)):
        x0, y0, x1, y1 = reg.bbox[c]
        m = np.zeros_like(target)
        m[y0:y1, x0:x1] = segmentation.region_mask(reg, c).astype(bool)
        best = max(best, (m & target).sum() / (m | target).sum())
    return best


def test_region_proposals_honour_a_deadline(l_block_bank):
    from service.vision.deadline import Deadline

    bank = l_block_bank
    truth = template_pose(bank, 40, 25.0, (380.0, 210.0), 650.0)
    image = checker_scene(bank, truth)
    kw = dict(distance_mm=None, distance_range_mm=DEFAULT_DISTANCE_RANGE_MM, n_out=5)
    full = regions.region_proposals(bank, image, K, (H, W), SEARCH_PARAMS, **kw)
    assert len(full) >= 3
    # no time for segmenting and matching: nothing is proposed, and the deadline says it stopped work
    none = Deadline(50.0, clock=lambda: 0.0)
    assert regions.region_proposals(bank, image, K, (H, W), SEARCH_PARAMS, deadline=none, **kw) == []
    assert none.hit
    # time for segmenting and matching, then 60 ms left, each reading of the clock 10 ms after the last:
    # a refinement starts while the previous one's 20 ms fit, so the two best are refined, as without one
    budget_ms = regions._PROPOSE_MS.high + 100.0
    calls = iter(range(1000))

    def clock() -> float:
        k = next(calls)  # 0: the deadline's start, 1: the check before segmenting
        return 0.0 if k < 2 else (budget_ms - 60.0) / 1000.0 + 0.010 * (k - 2)

    two = Deadline(budget_ms, clock=clock)
    two.checked()  # the region pass runs after the frame's first check, which it is not owed
    hs = regions.region_proposals(bank, image, K, (H, W), SEARCH_PARAMS, deadline=two, **kw)
    assert two.hit
    assert [(h.view, h.phi_deg, h.z_mm, tuple(h.uv)) for h in hs] == \
        [(h.view, h.phi_deg, h.z_mm, tuple(h.uv)) for h in full[:2]]


# --- the look-alike gate ---------------------------------------------------------------------------


def _mask_of(mesh, R: np.ndarray, z_mm: float) -> np.ndarray:
    """The mesh's silhouette (W x H, uint8 0/1), its bounding box's centre at depth z_mm on the axis."""
    V = np.asarray(mesh.vertices, float)
    c = (V.max(0) + V.min(0)) / 2
    _, face, (u0, v0) = rasterise_roi(V, np.asarray(mesh.faces), Pose(R, np.array([0.0, 0.0, z_mm]) - R @ c),
                                      K, (W, H))
    m = np.zeros((H, W), np.uint8)
    m[v0:v0 + face.shape[0], u0:u0 + face.shape[1]] = face >= 0
    return m


def _turns(m: np.ndarray) -> np.ndarray:
    """The mask's canonical rows at the turns ``propose`` tries for it."""
    import math

    import cv2

    mo = cv2.moments(m, True)
    ang, el = shapes.principal_axis(mo)
    turns = (0, 180) if el < shapes.ROUND_ELONG else range(0, 360, 30)
    return np.stack([shapes.canonical(m, mo, ang + math.radians(t)).ravel() for t in turns])


def _own(m: np.ndarray) -> np.ndarray:
    """A silhouette as a one-template canonical bank (per area scale), as ``canonical_templates``."""
    import cv2

    mo = cv2.moments(m, True)
    ang, _ = shapes.principal_axis(mo)
    return np.stack([shapes.canonical(m, mo, ang, s).ravel()[None] > 0.5 for s in shapes.SCALES])


@pytest.mark.parametrize("tilt_deg, z_mm", [(0, 600), (30, 600), (60, 600), (90, 600), (30, 300)])
def test_a_rendered_cylinder_is_explained_by_the_generic_family(tilt_deg, z_mm):
    import trimesh

    cyl = trimesh.creation.cylinder(radius=40, height=150, sections=64)
    m = _mask_of(cyl, Rx(tilt_deg), z_mm)
    assert shapes.best_iou(_turns(m), shapes.canonical_generic()) > 0.9


@pytest.mark.parametrize("part", ["sprayer", "lbracket"])
def test_a_part_view_with_its_own_shape_is_not_a_look_alike(data_dir, part):
    """The sprayer from the side (its neck and cap narrower than the body) and the L-bracket face-on are
    no generic shape; the part's own silhouette (a nearby view) explains them clearly better."""
    import trimesh

    mesh = trimesh.load(data_dir / "models" / f"{part}.stl", force="mesh")
    R = Rz(20.0) if part == "sprayer" else Ry(10.0)  # the sprayer's axis is y: across the line of sight
    region = _turns(_mask_of(mesh, R, 600.0))
    generic = shapes.best_iou(region, shapes.canonical_generic())
    own = shapes.best_iou(region, _own(_mask_of(mesh, R, 750.0)))  # the same view from farther
    assert generic < 0.9
    assert own > 0.95
    assert own - generic > max(0.05, regions.LOOKALIKE_MARGIN)  # clearly: above any margin tried


def test_the_gate_drops_every_region_at_an_impossible_margin(l_block_bank):
    """IoU is at most 1: a margin of 1 leaves no region (a generic shape always overlaps a little);
    the gate off keeps them."""
    bank = l_block_bank
    truth = Pose(Rz(25.0) @ Rx(-40.0) @ Ry(30.0), np.array([60.0, -30.0, 650.0]))
    image = checker_scene(bank, truth)
    props, _ = regions.propose(bank, image, K, DEFAULT_DISTANCE_RANGE_MM, n_out=5, lookalike_margin=1.0)
    assert props == []
    props, _ = regions.propose(bank, image, K, DEFAULT_DISTANCE_RANGE_MM, n_out=5, lookalike_margin=None)
    assert props and all(np.isnan(p.lookalike_gap) for p in props)


def test_the_gate_only_removes_proposals(l_block_bank):
    """A region the gate drops is not refilled: at a margin no region can miss (-inf) the proposals are
    the gate-off ones, each with its gap; at a margin of 1 none is left."""
    bank = l_block_bank
    truth = Pose(Rz(-30.0) @ Rx(50.0) @ Ry(-20.0), np.array([-40.0, 20.0, 700.0]))
    image = checker_scene(bank, truth)

    def keys(props):
        return [(p.region, p.hyp.view, round(p.hyp.phi_deg, 6), round(p.hyp.z_mm, 6)) for p in props]

    off, _ = regions.propose(bank, image, K, DEFAULT_DISTANCE_RANGE_MM, n_out=8, lookalike_margin=None)
    on, _ = regions.propose(bank, image, K, DEFAULT_DISTANCE_RANGE_MM, n_out=8, lookalike_margin=-np.inf)
    assert off and keys(on) == keys(off)
    assert all(np.isfinite(p.lookalike_gap) for p in on)
    assert regions.propose(bank, image, K, DEFAULT_DISTANCE_RANGE_MM, n_out=8, lookalike_margin=1.0)[0] == []
