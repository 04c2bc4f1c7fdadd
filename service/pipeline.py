"""The two pipelines as plain functions: ``build_templates`` (upload) and ``estimate`` (per frame).

The API, the CLI, the benchmarks and the tests all call these; they glue ``vision/`` together and
know nothing about HTTP, pydantic or the cache.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import trimesh

from service.vision import threads
from service.vision.bank import TemplateBank
from service.vision.estimate.chamfer import distance_tensor
from service.vision.estimate.coarse import SearchParams, coarse_search, poses_of
from service.vision.estimate.edges import detect_segments, to_grey_u8, undistort_segments
from service.vision.estimate.evidence import ColourFrame, colour_frame, evidence
from service.vision.estimate.verdict import Verdict, decide
from service.vision.geometry.camera import Intrinsics, undistort_image
from service.vision.geometry.frames import Pose, Rx, canonical_spin

DEFAULT_DISTANCE_RANGE_MM = (300.0, 1200.0)  # searched when the request gives no distance


@dataclass(frozen=True)
class PoseCandidate:
    pose: Pose  # T_cam_obj, mm
    cost: float  # mean directional chamfer distance, px (lower is better)
    score: float  # 0..1 fraction of border points with a matching image edge nearby (higher is better)


@dataclass(frozen=True)
class RefinedPose(PoseCandidate):
    iterations: int = 0
    inlier_ratio: float = 0.0


@dataclass(frozen=True)
class EstimateOutput:
    image_size: tuple[int, int]  # (w, h)
    found: bool
    coarse: PoseCandidate | None
    refined: RefinedPose | None
    candidates: list[PoseCandidate]
    timing_ms: dict[str, float]  # edges, coarse, refine, total
    overlay_png: bytes | None = None
    # the found/absent decision, its reason and the evidence it read (estimate/verdict.py)
    verdict: Verdict = field(default_factory=lambda: decide(None))


def build_templates(mesh: trimesh.Trimesh, *, symmetry: str = "auto", grid: dict | None = None,
                    progress: Callable[[float], None] | None = None) -> TemplateBank:
    """Mesh in mm -> template bank. ``symmetry``: "auto" | "none" | "x" | "y" | "z"."""
    threads.use_budget()
    from service.vision.build.templates import build_bank

    return build_bank(mesh, symmetry=symmetry, grid=grid or {}, progress=progress)


def template_picture(bank: TemplateBank, k: int) -> np.ndarray:
    """(H, W, 3) uint8 BGR picture of template k: projected mesh | extracted borderline."""
    from service.vision.build.templates import draw_template

    return draw_template(bank, k)


def _candidate(bank: TemplateBank, pose: Pose, cost: float, score: float) -> PoseCandidate:
    # A revolved part is reported with spin 0 about its axis (API.md: one canonical angle).
    return PoseCandidate(canonical_spin(pose, bank.symmetry_axis_obj, bank.symmetry_point_obj), float(cost),
                         float(score))


def _ms(t0: float) -> float:
    return (time.perf_counter() - t0) * 1000.0


# The search keeps as many polished hypotheses as the verdict checks.
SEARCH_PARAMS = SearchParams(n_polish=5)
N_VERIFY = 5  # candidates refined and verified per frame at most (best chamfer cost first): on 120
# synthetic clutter scenes the truth was the first proposal on 9, in the first 3 on 12, in the first 5 on 16
# (of 83 targets), in the first 10 on 17


def propose(bank: TemplateBank, image: np.ndarray, intr: Intrinsics, *, distance_mm: float | None = None,
            distance_range_mm: tuple[float, float] | None = None, params: SearchParams | None = None):
    """The proposal engine (the paper's method): LSD edges, their distance tensor and the coarse
    search -> (distinct candidates, lowest chamfer cost first; full-image segments; timing_ms with
    "edges" and "coarse")."""
    p = params or SEARCH_PARAMS
    threads.use_budget()
    t0 = time.perf_counter()
    grey = to_grey_u8(image)
    h, w = grey.shape
    seg = detect_segments(grey)
    if intr.dist is not None:
        # Straighten the edges once; everything after works in the ideal pinhole camera intr.K.
        seg = undistort_segments(seg, intr)
    # Level A's coarse grid is pooled from level B's (coarse_search): one set of distance transforms.
    dtt_b = distance_tensor(seg, n_channels=p.n_channels, scale=p.fine_scale)
    t_edges = _ms(t0)
    t1 = time.perf_counter()
    rng = distance_range_mm or DEFAULT_DISTANCE_RANGE_MM
    hyps = coarse_search(bank, dtt_b, intr, (h, w), p, distance_mm=distance_mm, distance_range_mm=rng)
    Rs, ts = poses_of(bank, hyps, intr.K, distance_mm) if hyps else (np.zeros((0, 3, 3)), np.zeros((0, 3)))
    cands = [_candidate(bank, Pose(R, t), hy.cost, hy.score) for R, t, hy in zip(Rs, ts, hyps, strict=True)]
    return distinct_candidates(cands, bank, intr.K), seg, {"edges": t_edges, "coarse": _ms(t1)}


def estimate(bank: TemplateBank, image: np.ndarray, intr: Intrinsics, *, distance_mm: float | None = None,
             distance_range_mm: tuple[float, float] | None = None, refine: bool = True, top_k: int = 5,
             overlay: bool = False, params: SearchParams | None = None,
             min_score: float | None = None) -> EstimateOutput:
    """Grey (H, W) or BGR (H, W, 3) image + intrinsics -> ranked poses and the verdict on the best.

    The coarse search proposes; up to ``N_VERIFY`` candidates are refined (also with ``refine``
    false: refinement is the check then, and ``refined`` stays null) and verified on the colour image
    (``verdict``); the one with the highest verification score is reported, found when that score
    reaches ``min_score`` (default ``verdict.MIN_SCORE``) and its distance lies in the searched range.
    """
    p = params or SEARCH_PARAMS
    t_start = time.perf_counter()
    grey = to_grey_u8(image)
    h, w = grey.shape
    cands, _, timing = propose(bank, grey, intr, distance_mm=distance_mm, distance_range_mm=distance_range_mm,
                               params=p)
    t0 = time.perf_counter()
    rng = None if distance_mm is not None else (distance_range_mm or DEFAULT_DISTANCE_RANGE_MM)
    # The evidence reads pixels where the ideal camera projects the model: undistort the frame once.
    frame = colour_frame(undistort_image(image, intr))
    checked = verify_candidates(bank, cands, grey, frame, intr, distance_mm=distance_mm,
                                distance_range_mm=rng, min_score=min_score, n_channels=p.n_channels)
    best = checked[0] if checked else None
    verdict = best.verdict if best is not None else decide(None)
    found = verdict.found
    coarse = best.candidate if found else None
    refined = best.refined if found and refine else None
    timing["refine"] = _ms(t0)
    png = None
    if overlay:
        from service.vision.overlay import draw_overlay, encode_png

        png = encode_png(draw_overlay(grey, bank, intr, coarse.pose if coarse else None,
                                      refined.pose if refined else None, found=found, score=verdict.score,
                                      rejected=None if found or best is None else best.refined.pose))
    timing["total"] = _ms(t_start)
    return EstimateOutput((w, h), found, coarse, refined, cands[:top_k], timing, png, verdict)


@dataclass(frozen=True)
class Checked:
    candidate: PoseCandidate  # as the coarse search proposed it
    refined: RefinedPose  # the pose refinement kept (the candidate itself when refinement lost score)
    verdict: Verdict


def verify_candidates(bank: TemplateBank, cands: list[PoseCandidate], grey: np.ndarray, frame: ColourFrame,
                      intr: Intrinsics, *, distance_mm: float | None,
                      distance_range_mm: tuple[float, float] | None, min_score: float | None,
                      n_channels: int) -> list[Checked]:
    """Refine and verify the best ``N_VERIFY`` candidates, best verification first. Stops at the first
    found one: the search ranks by chamfer cost, and on a clean frame the first is the truth."""
    out: list[Checked] = []
    for cand in cands[:N_VERIFY]:
        kept, verified, unexplained = _refine(bank, cand, grey, intr, distance_mm=distance_mm,
                                              n_channels=n_channels)
        ev = evidence(bank, kept.pose, intr, frame).as_dict()
        ev |= {"edge_support": verified, "unexplained": unexplained}
        v = decide(ev, z_mm=float(kept.pose.t_mm[2]), distance_range_mm=distance_range_mm,
                   min_score=min_score)
        out.append(Checked(cand, kept, v))
        if v.found:
            break
    out.sort(key=lambda c: (c.verdict.found, c.verdict.score), reverse=True)
    return out


def estimate_image(bank: TemplateBank, data: bytes, intr: Intrinsics, *, max_pixels: int,
                   check: Callable[[tuple[int, int]], None] | None = None, **options) -> EstimateOutput:
    """Image file bytes -> ``estimate`` (blocking: the API calls it from a worker thread; the CLI
    calls it too). ``check``, if given, is called with the decoded image's (w, h) before the search
    (it raises to refuse the request). ``options``: ``estimate``'s keyword arguments."""
    from service.decode import decode_image

    image = decode_image(data, max_pixels=max_pixels)
    if check is not None:
        check((image.shape[1], image.shape[0]))
    return estimate(bank, image, intr, **options)


def distinct_candidates(cands: list[PoseCandidate], bank: TemplateBank, K: np.ndarray) -> list[PoseCandidate]:
    """Drop candidates whose object centre projects within a quarter diameter of a better one."""
    out: list[PoseCandidate] = []
    centres = []
    for c in sorted(cands, key=lambda c: c.cost):
        x = c.pose.apply(bank.centre_obj[None])[0]
        uv = np.array([K[0, 0] * x[0] / x[2], K[1, 1] * x[1] / x[2]])
        r = 0.25 * K[0, 0] * bank.diameter_mm / max(x[2], 1e-6)
        if all(np.linalg.norm(uv - o) > r for o in centres):
            out.append(c)
            centres.append(uv)
    return out


def _refine(bank: TemplateBank, best: PoseCandidate, grey: np.ndarray, intr: Intrinsics, *,
            distance_mm: float | None, n_channels: int) -> tuple[RefinedPose, float, float]:
    """Refine a candidate; keep the refined pose only if it verifies at least as well.

    Also returns the verdict's evidence: the pose's score verified on the full-resolution edges (when
    the candidate is kept, the score it reports is the coarse, half-resolution one, which a textured
    floor can inflate), and its unexplained-edge ratio (``interior.unexplained_edge_ratio``)."""
    from service.vision.estimate.refine import refine_pose

    r = refine_pose(bank, best.pose, grey, intr, None, distance_mm=distance_mm, n_channels=n_channels)
    # r.score: the full-resolution score of r.pose, which is the candidate itself when refinement lost
    # score, else a pose scoring at least the candidate's there (less refine.SCORE_SLACK).
    if r.score < best.score:
        kept = RefinedPose(best.pose, best.cost, best.score, r.iterations, r.inlier_ratio)
    else:
        kept = RefinedPose(r.pose, float(r.cost), float(r.score), int(r.iterations),
                           float(r.inlier_ratio))
    return kept, float(r.score), r.unexplained


WARM_UP_POSE = Pose(Rx(60.0), np.array([5.0, -4.0, 300.0]))  # a cylinder, slightly off the optical axis


def warm_up() -> EstimateOutput:
    """Run the whole pipeline once on a small synthetic scene (a cylinder rendered 300 mm away), so
    that a fresh process loads or compiles its numba kernels before the first real frame (~0.5 s).
    Returns the estimate of the rendered cylinder (its known answer: ``WARM_UP_POSE``)."""
    from service.vision.geometry.render import render_shaded

    mesh = trimesh.creation.cylinder(radius=20.0, height=60.0, sections=24)
    bank = build_templates(mesh, symmetry="auto", grid={"view_step_deg": 30.0, "tilt_step_deg": 15.0,
                                                        "render_px": 96})
    intr = Intrinsics(300.0, 300.0, 159.5, 119.5)
    img = render_shaded(bank.vertices_mm, bank.faces, WARM_UP_POSE, intr.K, (320, 240))
    estimate(bank, img, intr)  # the unknown-distance path has kernels of its own
    return estimate(bank, img, intr, distance_mm=float(WARM_UP_POSE.t_mm[2]))

