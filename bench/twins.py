"""Mirror twins of found answers: would checking them turn a flipped answer into the right one?

On ``bench/instances.py``'s scenes (copies of the flat L-block, whose mirror plane is its mid-plane)
every instance is estimated with the twin check off; then, per found instance, its mirror twin
(``build/mirror.py``) is scored unrefined, refined and judged (``pipeline.check_candidate`` with the twin
check off). One row per found instance: its MSPD to the nearest copy (px at 640 px width) and score, the
twin's unrefined score, its refined score and MSPD to the nearest copy, and what the twin check keeps
("twin": the twin is found and scores higher).

    python bench/twins.py [--scenes 10] [--seed 3] [--weights w.json --min-score 0.97 --regions 12]
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from bench import instances as scenes  # noqa: E402
from service import pipeline  # noqa: E402
from service.vision.build.mirror import twin_poses  # noqa: E402
from service.vision.estimate import evidence, verdict  # noqa: E402
from service.vision.estimate.evidence import colour_frame  # noqa: E402


def nearest_px(checked, truth, pts) -> float:
    """MSPD (px at 640 px width) of a found instance or a checked twin to the copy nearest it."""
    return scenes.nearest_copies([checked], truth, pts)[0][1]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", type=int, default=10, help="scenes per background")
    ap.add_argument("--seed", type=int, default=3)
    ap.add_argument("--weights", type=Path, default=None, help="JSON verdict weights (else the service's)")
    ap.add_argument("--min-score", type=float, default=None)
    ap.add_argument("--regions", type=int, default=None)
    a = ap.parse_args()
    if a.weights:
        verdict.WEIGHTS.clear()
        verdict.WEIGHTS.update(json.loads(a.weights.read_text()))
        evidence.VISIBLE_PART = bool({"visible", "shading_r2_robust"} & set(verdict.WEIGHTS))
    if a.regions is not None:
        pipeline.REGION_PROPOSALS = a.regions
    pipeline.TWIN_CHECK = False
    bank = pipeline.build_templates(scenes.part(), symmetry="none",
                                    grid={"view_step_deg": 15.0, "render_px": 160})
    planes = pipeline.mirror_planes_of(bank)
    pts = bank.vertices_mm.astype(float)
    kw = dict(distance_mm=None, distance_range_mm=scenes.RANGE, min_score=a.min_score, n_channels=16)
    print("| floor | scene | found: MSPD px | score | twin unrefined | twin refined | twin MSPD px | kept |")
    print("|---|---|---|---|---|---|---|---|")
    for textured in (False, True):
        for i in range(a.scenes):
            rng = np.random.default_rng([a.seed, int(textured), i])
            n = int(rng.integers(2, 7))
            img, truth = scenes.scene(rng, bank, n, textured)
            out = pipeline.estimate(bank, img, scenes.INTR, distance_range_mm=scenes.RANGE, max_instances=n,
                                    min_score=a.min_score)
            frame = colour_frame(img)
            for inst in out.instances:
                pose = inst.refined.pose
                for twin in twin_poses(pose, planes):
                    raw = pipeline.unrefined_score(bank, twin, frame, scenes.INTR, None)
                    c = pipeline.check_candidate(bank, pipeline.PoseCandidate(twin, 0.0, 0.0), img[..., 0],
                                                 frame, scenes.INTR, **kw)
                    kept = "twin" if c.verdict.found and c.verdict.score > inst.verdict.score else "found"
                    floor = "textured" if textured else "plain"
                    print(f"| {floor} | {i} | {nearest_px(inst, truth, pts):.1f} | "
                          f"{inst.verdict.score:.3f} | {raw:.3f} | {c.verdict.score:.3f} | "
                          f"{nearest_px(c, truth, pts):.1f} | {kept} |")


if __name__ == "__main__":
    main()
