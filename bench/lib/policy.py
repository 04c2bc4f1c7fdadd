"""Bench options that run the estimate at another ``service.vision.pipeline.Policy``: a script adds them
(``add_policy_options``) and passes ``policy_of(args)`` to ``estimate(..., policy=...)``. Nothing here (or
anywhere in bench/) writes a service module's globals."""

from __future__ import annotations

import argparse
import json
from dataclasses import replace
from pathlib import Path

from service.vision.estimate.verdict import FEATURES
from service.vision.pipeline import DEFAULT_POLICY, Policy

# option -> (Policy field, type, help). Default: the service's value.
POLICY_OPTIONS: dict[str, tuple[str, type, str]] = {
    "--sweep-min-photos": ("sweep_min_photos", int,
                           "parts calibrated on this many photos or more have a last pass of silhouettes "
                           "swept over the taught colours (estimate/colour_sweep.py; 2: every calibrated "
                           "part, 1000: none)"),
    "--range-hold-max": ("range_hold_max", float,
                         "a refinement ending past the searched range by at most this share is refined again "
                         "at its bound (0: none)"),
    "--calibration-margin": ("calibration_margin", float, "logit margin over the highest wrong score"),
}
# ... and the gradient search on a plane (``Policy.gradient``): option -> (field, type, help).
GRADIENT_OPTIONS: dict[str, tuple[str, type, str]] = {
    "--rivals": ("rivals", int, "other rotations proposed at each gradient match's place (0: none)"),
    "--rival-margin": ("rival_margin", float, "a rival scores within this of the match"),
}
# ... and the taught search of a part not calibrated (``Policy.taught_search``): option -> field.
TAUGHT_OPTIONS = {"--colour-prior": "colour_prior", "--scored-fits": "scored_fits",
                  "--order-first": "order_first", "--polish-from": "polish_from"}


def add_policy_options(ap: argparse.ArgumentParser) -> None:
    for option, (field, kind, text) in POLICY_OPTIONS.items():
        ap.add_argument(option, type=kind, default=None,
                        help=f"{text} (Policy.{field}; default: the service's)")
    for option, (field, kind, text) in GRADIENT_OPTIONS.items():
        ap.add_argument(option, type=kind, default=None,
                        help=f"{text} (Policy.gradient.{field}; default: the service's)")
    ap.add_argument("--colour-prior", action="store_true",
                    help="taught parts not calibrated: region proposals ranked by the colour prior")
    ap.add_argument("--scored-fits", type=int, default=None,
                    help="taught parts not calibrated: region fits scored before the best are refined "
                         "(48 measured)")
    ap.add_argument("--order-first", action="store_true",
                    help="taught parts not calibrated: candidates ordered before near duplicates are dropped")
    ap.add_argument("--polish-from", type=float, default=None,
                    help="taught parts not calibrated: near misses from this score are polished")
    ap.add_argument("--weights", type=Path, default=None,
                    help="JSON verdict weights (bench/fit_verdict.py --save) for parts without taught "
                         "colours instead of the service's (Policy.verdict_weights)")


def verdict_weights(path: Path) -> tuple[tuple[str, float], ...]:
    """A ``bench/fit_verdict.py --save`` file as ``Policy.verdict_weights``."""
    w = json.loads(path.read_text())
    unknown = set(w) - {"bias", *FEATURES}
    if "bias" not in w or unknown:
        raise ValueError(f"{path}: verdict weights need a 'bias' and read only the verdict's evidence "
                         f"(verdict.FEATURES); not measured: {sorted(unknown)}")
    return tuple(sorted((str(k), float(v)) for k, v in w.items()))


def policy_of(a: argparse.Namespace) -> Policy:
    """The service's policy with every option given in ``a`` (a flag only when given)."""
    def given(option: str):
        value = getattr(a, option.lstrip("-").replace("-", "_"), None)
        return None if value is False else value

    fields = {f: given(o) for o, (f, _, _) in POLICY_OPTIONS.items() if given(o) is not None}
    if given("--weights") is not None:
        fields["verdict_weights"] = verdict_weights(given("--weights"))
    taught = {f: given(o) for o, f in TAUGHT_OPTIONS.items() if given(o) is not None}
    gradient = {f: given(o) for o, (f, _, _) in GRADIENT_OPTIONS.items() if given(o) is not None}
    return replace(DEFAULT_POLICY, **fields, taught_search=replace(DEFAULT_POLICY.taught_search, **taught),
                   gradient=replace(DEFAULT_POLICY.gradient, **gradient))
