"""Silhouettes swept over the taught colours (``vision/estimate/colour_sweep.py``): where a frame is coloured
like the part in the part's own silhouette, the sweep proposes that silhouette's pose, also half hidden."""

import cv2
import numpy as np

from service.vision.estimate import colour_sweep
from service.vision.estimate.search import poses_of
from service.vision.geometry.frames import Pose
from service.vision.geometry.render import rasterise_roi
from tests.test_regions import H, K, W, template_pose

SCALE = 0.5  # the likelihood's working px per frame px (segmentation.WORK_WIDTH 320 of 640)
RANGE_MM = (300.0, 1200.0)
PART, FRAME = 0.95, 0.05  # likelihood of a part-coloured pixel and of any other
# The sweep's grid: depths 1.26 apart (7 over 300-1200 mm), angles 15 deg, a template 15 deg from the
# next: its best placement's silhouette overlaps the painted one at least this much
MIN_IOU = 0.6
CENTRE_TOL = 0.15  # of the part's projected diameter: the best placement's centre off the painted one's


def _silhouette(bank, pose: Pose) -> np.ndarray:
    _, face, (u0, v0) = rasterise_roi(bank.vertices_mm, bank.faces, pose, K, (W, H))
    m = np.zeros((H, W), bool)
    m[v0:v0 + face.shape[0], u0:u0 + face.shape[1]] = face >= 0
    return m


def _likelihood(mask: np.ndarray) -> np.ndarray:
    full = np.where(mask, PART, FRAME).astype(np.float32)
    return cv2.resize(full, (int(W * SCALE), int(H * SCALE)), interpolation=cv2.INTER_AREA)


def _centre_uv(bank, pose: Pose) -> np.ndarray:
    c = pose.R @ bank.centre_obj + pose.t_mm
    return (K @ c)[:2] / c[2]


def _best(bank, hyps, truth: Pose) -> tuple[float, float]:
    """Of the hypotheses, the highest silhouette IoU with the truth's and its centre's offset (px)."""
    want = _silhouette(bank, truth)
    Rs, ts = poses_of(bank, hyps, K, None)
    best = (0.0, np.inf)
    for R, t in zip(Rs, ts, strict=True):
        got = _silhouette(bank, Pose(R, t))
        iou = float((got & want).sum() / max((got | want).sum(), 1))
        if iou > best[0]:
            best = (iou, float(np.linalg.norm(_centre_uv(bank, Pose(R, t)) - _centre_uv(bank, truth))))
    return best


def _diameter_px(bank, pose: Pose) -> float:
    return bank.diameter_mm * K[0, 0] / float(pose.t_mm[2])


def test_a_blob_of_the_part_s_colour_is_the_first_location():
    L = colour_sweep.log_odds(np.full((120, 160), FRAME, np.float32))
    cv2.circle(L, (100, 50), 12, float(colour_sweep.log_odds(np.float32([PART]))[0]), -1)
    locations = colour_sweep.blob_locations(L, [8.0, 12.0, 18.0], 5)
    assert np.hypot(locations[0][0] - 100, locations[0][1] - 50) <= 2.0


def test_a_frame_without_the_part_s_colour_has_no_location(l_block_bank):
    lik = np.full((int(H * SCALE), int(W * SCALE)), FRAME, np.float32)
    assert colour_sweep.colour_sweep(l_block_bank, lik, K, SCALE, RANGE_MM) == []


def test_the_sweep_proposes_the_painted_silhouette_s_pose(l_block_bank):
    bank = l_block_bank
    truth = template_pose(bank, 40, 25.0, (380.0, 210.0), 650.0)
    lik = _likelihood(_silhouette(bank, truth))
    hyps = colour_sweep.colour_sweep(bank, lik, K, SCALE, RANGE_MM)
    iou, off = _best(bank, hyps[:colour_sweep.PER_LOCATION], truth)  # the first blob's placements
    assert iou >= MIN_IOU
    assert off <= CENTRE_TOL * _diameter_px(bank, truth)


def test_a_half_hidden_part_is_still_proposed(l_block_bank):
    bank = l_block_bank
    truth = template_pose(bank, 40, 25.0, (380.0, 210.0), 650.0)
    mask = _silhouette(bank, truth)
    cols = np.flatnonzero(mask.any(0))
    hidden = mask.copy()
    # an occluder over the part's left 40 % (not part-coloured)
    hidden[:, :cols[0] + int(0.4 * (cols[-1] - cols[0]))] = False
    assert hidden.sum() < 0.75 * mask.sum()
    hyps = colour_sweep.colour_sweep(bank, _likelihood(hidden), K, SCALE, RANGE_MM)
    iou, off = _best(bank, hyps, truth)
    assert iou >= MIN_IOU
    assert off <= CENTRE_TOL * _diameter_px(bank, truth)


def test_the_search_s_last_pass_proposes_the_part_painted_in_its_colours(l_block_bank):
    """``pipeline.propose`` with ``sweep_colours``: its last deferred pass holds the painted part's pose."""
    from service.vision.estimate import colour_prior
    from service.vision.geometry.camera import Intrinsics
    from service.vision.pipeline import propose

    bank = l_block_bank
    truth = template_pose(bank, 40, 25.0, (380.0, 210.0), 650.0)
    red = (40, 40, 200)
    image = np.full((H, W, 3), 128, np.uint8)
    image[_silhouette(bank, truth)] = red
    passes: list = []
    propose(bank, image, Intrinsics.from_K(K), distance_range_mm=RANGE_MM, deferred=passes, colour=image,
            part_colours=colour_prior.part_density(np.array([red] * 4, np.float32), np.ones(4)),
            order=lambda cands: cands, sweep_colours=True)
    cands = passes[-1]()
    assert cands
    want = _silhouette(bank, truth)
    ious = [float((_silhouette(bank, c.pose) & want).sum() / (_silhouette(bank, c.pose) | want).sum())
            for c in cands]
    assert max(ious) >= MIN_IOU
