"""The proposal engine for a part that projects small in a small frame (Linemod-sized objects in a
640 x 480 photo): its proposals come from the colour image's Canny edges (``colour_edges``).

LSD on the half-size grey image, which the paper's grid was tuned with (200-800 px parts at
1280 x 960), finds a fifth of such a part's outline on real photos (a dark blue part on a brown table
has almost no grey edge, and LSD breaks short curved outlines into nothing). ``bench/stages.py`` on
39 ``lmo_dev`` queries (distance not given, the pipeline's 12 peaks): outline coverage at the truth
0.19 -> 0.47, a level-A peak near the truth 3 -> 11, the truth among the proposals 0 -> 2, level B
started from the truth's own level-A cell reaching it 18 -> 34; search 1185 -> 1305 ms p50. Level A
at twice its resolution on top proposed 3 instead of 2 at 3.7 x the search time: not kept.
"""

from __future__ import annotations

from service.vision.bank import TemplateBank
from service.vision.geometry.camera import Intrinsics

# A part whose projected diameter at the far end of the searched distances is under this many
# full-resolution pixels ...
SMALL_PART_PX = 130.0
# ... in a frame of at most this many pixels is searched on colour edges. Larger frames keep LSD: on
# 1280 x 960 clutter colour edges proposed no more truths (1 of 16 with, 0 without, distance given)
# and cost more there.
SMALL_MAX_PIXELS = 640 * 480


def far_size_px(bank: TemplateBank, intr: Intrinsics, distance_mm: float | None,
                distance_range_mm: tuple[float, float]) -> float:
    """The part's diameter projected at the largest distance searched, px."""
    z_far = distance_mm if distance_mm is not None else distance_range_mm[1]
    return max(intr.fx, intr.fy) * bank.diameter_mm / max(float(z_far), 1e-6)


def is_small(bank: TemplateBank, intr: Intrinsics, image_shape: tuple[int, int], distance_mm: float | None,
             distance_range_mm: tuple[float, float]) -> bool:
    """Search on colour edges: the part projects under ``SMALL_PART_PX`` at the far end of the searched
    distances in a frame (``image_shape`` = (h, w)) of at most ``SMALL_MAX_PIXELS``."""
    return (image_shape[0] * image_shape[1] <= SMALL_MAX_PIXELS
            and far_size_px(bank, intr, distance_mm, distance_range_mm) < SMALL_PART_PX)
