"""The region proposals' numba merging and batched matching (``vision/estimate/regions.py``) against the
reference written for clarity (``vision/reference/regions.py``): the same hierarchy (every node's
children, area, box, moments, and the contrasts at which it formed and merged away) and the same
proposals, on random images with many equal contrasts (ties in the heap) and on real photos."""

import cv2
import numpy as np
import pytest

from service.vision.estimate import regions, segmentation, shapes
from service.vision.pipeline import DEFAULT_DISTANCE_RANGE_MM
from service.vision.reference import regions as ref

FIELDS = ("labels", "children", "area", "bbox", "born", "died", "moments")


def key(p: regions.RegionProposal) -> tuple:
    return p.region, p.iou, p.hyp.view, p.hyp.phi_deg, p.hyp.z_mm, tuple(p.hyp.uv)


def assert_same_regions(a: segmentation.Regions, b: segmentation.Regions) -> None:
    assert a.scale == b.scale
    for f in FIELDS:
        np.testing.assert_array_equal(getattr(a, f), getattr(b, f), err_msg=f)


def blocky_lab(rng: np.random.Generator, h: int, w: int, n_levels: int) -> np.ndarray:
    """A Lab image of random rectangles in a few quantised colours (so many boundaries share one mean
    contrast exactly), with single-pixel specks."""
    lab = np.zeros((h, w, 3), np.float32)
    for _ in range(rng.integers(5, 40)):
        y0, x0 = rng.integers(0, h), rng.integers(0, w)
        y1, x1 = y0 + rng.integers(1, h // 2 + 2), x0 + rng.integers(1, w // 2 + 2)
        lab[y0:y1, x0:x1] = rng.integers(0, n_levels, 3) * 7.0
    ys, xs = rng.integers(0, h, 30), rng.integers(0, w, 30)
    lab[ys, xs] = rng.integers(0, n_levels, (30, 3)) * 7.0
    return lab


@pytest.mark.parametrize("seed", range(12))
def test_the_merge_kernel_builds_the_reference_hierarchy_with_ties(seed):
    rng = np.random.default_rng(seed)
    h, w = int(rng.integers(8, 60)), int(rng.integers(8, 80))
    lab = blocky_lab(rng, h, w, n_levels=int(rng.integers(2, 6)))
    labels, n0, dh, dv = segmentation.initial_regions(lab)
    st = segmentation.region_stats(labels, n0, dh, dv)
    a, b = ref.merge_py(labels, 0.5, st), segmentation.merge(labels, 0.5, st)
    assert_same_regions(a, b)
    # a hierarchy: every merged node's area is its children's, and it forms no weaker than they did
    merged = a.children[:, 0] >= 0
    assert np.array_equal(a.area[merged], a.area[a.children[merged, 0]] + a.area[a.children[merged, 1]])
    # and the heap met ties: merges at exactly one contrast, ordered by their regions' ids
    assert len(np.unique(a.born[merged])) < merged.sum()


def test_a_single_region_image_has_one_node():
    labels, n0, dh, dv = segmentation.initial_regions(np.zeros((6, 9, 3), np.float32))
    reg = segmentation.merge(labels, 1.0, segmentation.region_stats(labels, n0, dh, dv))
    assert len(reg.area) == 1 and reg.area[0] == 54 and reg.children[0].tolist() == [-1, -1]


def noisy_scene(rng: np.random.Generator) -> np.ndarray:
    img = (rng.random((120, 160, 3)) * 255).astype(np.uint8)
    img = cv2.GaussianBlur(img, (0, 0), 2.0)
    cv2.rectangle(img, (40, 30), (90, 70), (40, 150, 210), -1)
    cv2.circle(img, (120, 80), 18, (200, 60, 60), -1)
    return img


@pytest.mark.parametrize("seed", range(3))
def test_segment_matches_the_reference_on_noisy_scenes(seed):
    img = noisy_scene(np.random.default_rng(seed))
    assert_same_regions(ref.segment_py(img), segmentation.segment(img))


@pytest.mark.slow
def test_segment_and_proposals_match_the_reference_on_real_photos(data_dir, monkeypatch):
    import json

    import trimesh

    from service.vision.pipeline import build_templates

    for name, idx in (("clutter2", 4), ("absent2", 23), ("lmo_dev", 0)):
        set_dir = data_dir / name
        g = json.loads((set_dir / "gt.jsonl").read_text().splitlines()[idx])
        bank = build_templates(trimesh.load(set_dir / "models" / f"{g['model']}.stl", force="mesh"),
                               symmetry="auto")
        img = cv2.imread(str(set_dir / g["image"]), cv2.IMREAD_UNCHANGED)[..., :3]
        K = np.asarray(g["K"], float)
        reg_a, reg_b = ref.segment_py(img), segmentation.segment(img)
        assert_same_regions(reg_a, reg_b)
        for n_out in (30, 5, 1):
            pa, _ = ref.propose_py(bank, img, K, DEFAULT_DISTANCE_RANGE_MM, n_out=n_out, reg=reg_a)
            # the reference has no look-alike gate
            pb, _ = regions.propose(bank, img, K, DEFAULT_DISTANCE_RANGE_MM, n_out=n_out, reg=reg_b,
                                    lookalike_margin=None)
            assert 0 < len(pa) <= n_out
            assert [key(p) for p in pa] == [key(p) for p in pb]


@pytest.mark.parametrize("levels", [None, 40, 6])
def test_best_fits_are_the_positive_head_of_a_full_sort(levels):
    # continuous IoUs (no ties), coarsely quantised ones (ties at and inside the first 12) and zeros
    rng = np.random.default_rng(7)
    iou = rng.random((60, 826)).astype(np.float32)
    iou[rng.random(iou.shape) < 0.6] = 0
    iou[:5, 3:] = 0  # rows with fewer positive fits than asked
    if levels:
        iou = np.round(iou * levels).astype(np.float32) / np.float32(levels)
    got = regions._best_fits(iou, 12)
    for row, (idx, vals) in zip(iou, got, strict=True):
        best = np.argsort(-row)[:12]
        pos = [(int(i), float(row[i])) for i in best if row[i] > 0]
        assert [(i, v) for i, v in zip(idx, vals, strict=True) if v > 0] == pos


def test_region_masks_from_leaf_ranges_are_the_reference_masks():
    reg = segmentation.segment(noisy_scene(np.random.default_rng(5)))
    for c in range(len(reg.area)):
        m = segmentation.region_mask(reg, c)
        np.testing.assert_array_equal(m, ref.region_mask_py(reg, c))
        assert m.sum() == reg.area[c]  # and every pixel of the node is in its box


def test_canonical_turns_are_canonical_at_each_turn():
    rng = np.random.default_rng(3)
    for _ in range(40):
        m = (rng.random((int(rng.integers(5, 50)), int(rng.integers(5, 50)))) > 0.3).astype(np.uint8)
        mo = cv2.moments(m, True)
        angles = list(rng.uniform(0.0, 7.0, 12))
        out = np.empty((12, shapes.CANON_PX ** 2), np.float32)
        shapes.canonical_turns(m.astype(np.float32), mo, angles, out)
        for a, row in zip(angles, out, strict=True):
            np.testing.assert_array_equal(row, shapes.canonical(m, mo, a).ravel())
