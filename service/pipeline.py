"""The two pipelines as plain functions: ``build_templates`` (upload) and ``estimate`` (per frame).

The API, the CLI, the benchmarks and the tests all call these; they glue ``vision/`` together and
know nothing about HTTP, pydantic or the cache.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import trimesh

from service.vision import threads
from service.vision.bank import TemplateBank
from service.vision.estimate.chamfer import distance_tensor
from service.vision.estimate.coarse import SearchParams, coarse_search, poses_of
from service.vision.estimate.edges import detect_segments, to_grey_u8, undistort_segments
from service.vision.estimate.interior import unexplained_edge_ratio
from service.vision.estimate.verdict import Verdict, decide, needs_refined_check, screen
from service.vision.geometry.camera import Intrinsics
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
    # the found/absent decision and the evidence it read (estimate/verdict.py); None from callers that
    # make an EstimateOutput without the pipeline (bench/accuracy.py --selftest)
    verdict: Verdict | None = None


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


def estimate(bank: TemplateBank, image: np.ndarray, intr: Intrinsics, *, distance_mm: float | None = None,
             distance_range_mm: tuple[float, float] | None = None, refine: bool = True, top_k: int = 5,
             overlay: bool = False, params: SearchParams | None = None) -> EstimateOutput:
    """Grey (H, W) uint8/uint16 image + intrinsics -> ranked poses (see EstimateOutput)."""
    p = params or SearchParams()
    threads.use_budget()
    t_start = time.perf_counter()
    grey = to_grey_u8(image)
    h, w = grey.shape
    seg = detect_segments(grey)
    if intr.dist is not None:
        # Straighten the edges once; everything after works in the ideal pinhole camera intr.K.
        seg = undistort_segments(seg, intr)
    # Level A's coarse grid is pooled from level B's (coarse_search): one set of distance transforms.
    dtt_b = distance_tensor(seg, n_channels=p.n_channels, scale=p.fine_scale)
    t_edges = _ms(t_start)

    t0 = time.perf_counter()
    rng = distance_range_mm or DEFAULT_DISTANCE_RANGE_MM
    hyps = coarse_search(bank, dtt_b, intr, (h, w), p, distance_mm=distance_mm, distance_range_mm=rng)
    Rs, ts = poses_of(bank, hyps, intr.K, distance_mm) if hyps else (np.zeros((0, 3, 3)), np.zeros((0, 3)))
    cands = [_candidate(bank, Pose(R, t), hy.cost, hy.score) for R, t, hy in zip(Rs, ts, hyps, strict=True)]
    cands = distinct_candidates(cands, bank, intr.K)[:top_k]
    t_coarse = _ms(t0)

    best = cands[0] if cands else None
    verdict = screen(None if best is None else best.score)
    refined = None
    t0 = time.perf_counter()
    if verdict is None and needs_refined_check(best.score, refine=refine):
        checked, verified, unexplained = _refine(bank, cands, grey, intr, distance_mm=distance_mm,
                                                 n_channels=p.n_channels)
        verdict = decide(best.score, verified_score=verified, unexplained=unexplained)
        if verdict.found and refine:
            refined = checked
    elif verdict is None:  # a coarse score as high as a refined one's: check its inside only, on the
        # coarse stage's half-resolution segments (paper renders' true poses <= 0.20 on them)
        unexplained = unexplained_edge_ratio(bank, best.pose, intr, seg, (w, h))
        verdict = decide(best.score, unexplained=unexplained)
    found = verdict.found
    coarse = best if found else None
    t_refine = _ms(t0)
    png = None
    if overlay:
        from service.vision.overlay import draw_overlay, encode_png

        shown = refined or coarse or (cands[0] if cands else None)
        png = encode_png(draw_overlay(grey, bank, intr, coarse.pose if coarse else None,
                                      refined.pose if refined else None, found=found,
                                      score=shown.score if shown else None))
    timing = {"edges": t_edges, "coarse": t_coarse, "refine": t_refine, "total": _ms(t_start)}
    return EstimateOutput((w, h), found, coarse, refined, cands, timing, png, verdict)


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


def _refine(bank: TemplateBank, cands: list[PoseCandidate], grey: np.ndarray, intr: Intrinsics, *,
            distance_mm: float | None, n_channels: int) -> tuple[RefinedPose, float, float]:
    """Refine the best candidate; keep the refined pose only if it verifies at least as well.

    Also returns the verdict's evidence: the pose's score verified on the full-resolution edges (when
    the candidate is kept, the score it reports is the coarse, half-resolution one, which a textured
    floor can inflate), and its unexplained-edge ratio (``interior.unexplained_edge_ratio``)."""
    from service.vision.estimate.refine import refine_pose

    best = cands[0]
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

