"""A part's colours taught from reference photos, and the teach-time calibration of its operating point.

A taught part's colours may not set it apart from the cell's other things (a white glue bottle on white
clutter), so the global operating point lets wrong poses through. Each reference photo shows the part at a
known pose among the cell's own things: searched like a frame, taught by the other photos, every pose
judged there far from the known one is a wrong answer the cell can produce, and the part's operating point
(``Policy.operating_point``) is set a margin above the highest such score.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, replace

import cv2
import numpy as np

from service.vision.bank import TemplateBank
from service.vision.estimate.evidence import ColourFrame, colour_frame, evidence
from service.vision.geometry.camera import Intrinsics, undistort_image
from service.vision.geometry.frames import Pose
from service.vision.model.appearance import (
    MIN_AGREEMENT_KNOWN,
    Appearance,
    ReferenceView,
    ViewColours,
    colour_spread,
    combine,
    read_views,
    spun,
    teach,
)
from service.vision.pipeline.check import NOT_POLISHED
from service.vision.pipeline.estimate import estimate
from service.vision.pipeline.policy import DEFAULT_POLICY, Policy
from service.vision.pipeline.types import Checked
from service.vision.reference.metrics import mspd_px, symmetry_rotations

_NEVER = 2.0  # a min_score no pose reaches: every candidate is judged


def teach_appearance(bank: TemplateBank, views: list[tuple], *, calibrate: bool = False,
                     policy: Policy = DEFAULT_POLICY) -> Appearance:
    """The part's colours (``model/appearance.py``) from reference photos: each a decoded image (BGR, or
    grey), its camera and the part's pose in it (T_cam_obj), and optionally an (H, W) bool mask of the
    pixels where something else hides the part. A revolved part is taught per ring about its axis
    (``appearance.SPIN_VIEWS``). Whether an estimate uses them (``Appearance.used``): the untextured
    shading model's fit at each photo's pose says whether the part is plain, and each photo judged on
    the colours the others teach whether the photos agree. ``calibrate``: the part's operating point is
    calibrated on the photos too (``calibrate_appearance``: seconds a photo)."""
    if not views:
        return teach(bank.vertices_mm, bank.faces, [])
    taught = _read_references(bank, views)
    face_bgr = combine(bank.faces, taught.seen)
    agree = []
    for i, (_, intr, pose, *_) in enumerate(views if len(views) >= 2 else []):
        ev = evidence(bank, pose, intr, taught.frames[i], face_bgr=taught.without(bank, i))
        if ev.appearance_known is not None and ev.appearance_known >= MIN_AGREEMENT_KNOWN:
            agree.append(ev.appearance)
    appearance = Appearance(face_bgr, len(views), float(np.median(taught.shading_r2)),
                            colour_spread(face_bgr), float(np.median(agree)) if agree else float("nan"))
    return calibrate_appearance(bank, views, appearance, taught, policy=policy) if calibrate else appearance


@dataclass(frozen=True)
class References:
    """What the reference photos show: each photo's colour frame (ideal camera), the shading model's fit
    at its pose, the colours every (spun) view reads, and which photo each view is."""
    frames: list[ColourFrame]
    shading_r2: list[float]
    seen: ViewColours
    photo_of: np.ndarray

    def without(self, bank: TemplateBank, i: int) -> np.ndarray:
        """(F, 3) the face colours the photos other than ``i`` teach."""
        return combine(bank.faces, self.seen, self.photo_of != i)


def _read_references(bank: TemplateBank, views: list[tuple]) -> References:
    refs, photo_of, shading_r2, frames = [], [], [], []
    for i, (image, intr, pose, *hidden) in enumerate(views):
        bgr = image if image.ndim == 3 else cv2.cvtColor(image, cv2.COLOR_GRAY2BGR)
        frame = colour_frame(undistort_image(bgr[..., :3], intr))
        frames.append(frame)
        shading_r2.append(evidence(bank, pose, intr, frame).shading_r2)
        poses = [pose] if bank.symmetry_axis_obj is None else spun(pose, bank.symmetry_axis_obj,
                                                                    bank.symmetry_point_obj)
        refs += [ReferenceView(frame.bgr, intr, p, hidden[0] if hidden else None) for p in poses]
        photo_of += [i] * len(poses)
    seen = read_views(bank.vertices_mm, bank.faces, refs)
    return References(frames, shading_r2, seen, np.asarray(photo_of))


def calibrate_appearance(bank: TemplateBank, views: list[tuple], appearance: Appearance,
                         taught: References | None = None,
                         progress: Callable[[int, int], None] | None = None, *,
                         policy: Policy = DEFAULT_POLICY) -> Appearance:
    """``appearance`` with its ``wrong_score``: the highest verification score of a wrong pose judged when
    each reference photo is searched (``estimate``, every candidate judged, as the calibrated part will
    be), taught by the others. Needs two photos whose colours can be calibrated
    (``Appearance.calibratable``); else ``appearance`` as it is. ``progress(done, total)`` is told before
    each photo's search (seconds each) and may raise to stop."""
    if len(views) < 2 or not appearance.calibratable:
        return appearance
    taught = taught or _read_references(bank, views)
    wrong = -math.inf
    for i, (image, intr, pose, *_) in enumerate(views):
        if progress is not None:
            progress(i, len(views))
        others = replace(appearance, face_bgr=taught.without(bank, i), calibrated_photos=len(views))
        out = estimate(bank, image, intr, min_score=_NEVER, appearance=others, policy=policy)
        for c in out.checked:
            if _counts_as_met(c, policy) and pose_error_px(bank, c.refined.pose, pose, intr, image.shape[1],
                                                           policy) >= policy.calibration_wrong_px:
                wrong = max(wrong, c.verdict.score)
    return replace(appearance, wrong_score=wrong, calibrated_photos=len(views))


def _counts_as_met(c: Checked, policy: Policy = DEFAULT_POLICY) -> bool:
    """A judged pose the cell could answer: not refused for where it lies, except one mostly inside the
    photo (``policy.calibration_min_in_image``) that its border cut: the cell produces that score too."""
    if c.verdict.reason == "outside_image":
        return c.verdict.evidence.get("in_image", 0.0) >= policy.calibration_min_in_image
    return c.verdict.reason not in NOT_POLISHED


def pose_error_px(bank: TemplateBank, pose: Pose, truth: Pose, intr: Intrinsics, width: int,
                  policy: Policy = DEFAULT_POLICY) -> float:
    """MSPD (a revolved part's spins about its axis alike) between two poses, pixels at 640 wide."""
    v = np.asarray(bank.vertices_mm, float)
    v = v[:: max(1, len(v) // policy.calibration_points)]
    syms = None if bank.symmetry_axis_obj is None else symmetry_rotations(
        bank.symmetry_axis_obj, bank.symmetry_point_obj, n=72)
    return mspd_px(pose.R, pose.t_mm, truth.R, truth.t_mm, intr.K, v, syms) * 640.0 / width
