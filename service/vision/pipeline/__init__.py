"""The two pipelines as plain functions: ``build_templates`` (upload) and ``estimate`` (per frame).

The API, the CLI, the benchmarks and the tests all call these; they glue ``vision/`` together and know
nothing about HTTP, pydantic or the cache. One frame's story is ``estimate.py``: ``propose.py`` proposes,
``check.py`` refines, measures the evidence and asks ``estimate/verdict.py`` for found / absent,
``instances.py`` does so for several copies; ``teach.py`` teaches a part's colours and calibrates its
operating point. Every tuned number is in ``policy.py``: pass another ``Policy`` to change one.
"""

from service.vision.pipeline.build import build_templates, template_picture
from service.vision.pipeline.check import (
    NOT_POLISHED,
    Checker,
    check_candidate,
    judge,
    polish_appearance,
    same_place_but_depth,
    verify_candidates,
)
from service.vision.pipeline.estimate import (
    answer_verdict,
    appearance_in_use,
    estimate,
    estimate_image,
    judged_range,
    misscaled_request,
)
from service.vision.pipeline.instances import SORTS, sort_instances, verify_instances
from service.vision.pipeline.part import mirror_planes_of, resting_rotations
from service.vision.pipeline.place import silhouette_iou
from service.vision.pipeline.policy import (
    DEFAULT_DISTANCE_RANGE_MM,
    DEFAULT_POLICY,
    Policy,
    TaughtSearch,
    operating_point,
    search_params,
    taught_search,
)
from service.vision.pipeline.propose import distinct_candidates, propose, taught_colour_density
from service.vision.pipeline.teach import calibrate_appearance, teach_appearance
from service.vision.pipeline.types import Checked, EstimateOutput, Instance, PoseCandidate, RefinedPose
from service.vision.pipeline.unrefined import by_unrefined_score, unrefined_score
from service.vision.pipeline.warm_up import WARM_UP_POSE, warm_up

__all__ = [
    "DEFAULT_DISTANCE_RANGE_MM", "DEFAULT_POLICY", "NOT_POLISHED", "SORTS", "WARM_UP_POSE", "Checked",
    "Checker", "EstimateOutput", "Instance", "Policy", "PoseCandidate", "RefinedPose", "TaughtSearch",
    "answer_verdict", "appearance_in_use", "build_templates", "by_unrefined_score", "calibrate_appearance",
    "check_candidate", "distinct_candidates", "estimate", "estimate_image", "judge", "judged_range",
    "mirror_planes_of", "misscaled_request", "operating_point", "polish_appearance", "propose",
    "resting_rotations", "same_place_but_depth", "search_params", "silhouette_iou", "sort_instances",
    "taught_colour_density", "taught_search", "teach_appearance", "template_picture", "unrefined_score",
    "verify_candidates", "verify_instances", "warm_up",
]
