"""A part's plane calibration (``pipeline/plane_calibration``) as the service makes it at upload, its
records kept in bench/out/plane_calibration/ per (bank, scenes) and made again only when missing."""

from __future__ import annotations

import hashlib
import json
import sys
import time
from dataclasses import asdict
from pathlib import Path

from bench.lib.data import OUT_DIR, ROOT, bank_path
from service.vision.bank import TemplateBank
from service.vision.estimate.verdict import AGREEMENT_EVIDENCE
from service.vision.pipeline.plane_calibration import (
    MARGIN,
    PlaneCalibration,
    PlaneRecord,
    calibrated,
    plane_records,
)
from service.vision.pipeline.policy import DEFAULT_POLICY, Policy


def _method(policy: Policy) -> str:
    """A hash of the vision core's code and of the policy: any change to what proposes, refines, checks or
    renders a calibration's candidates makes the records again (the operating point is derived from them
    at every load: ``calibrated``). A hash of a few files let records outlive a change to the gradient
    search that proposes their candidates."""
    scenes = b"".join(f.read_bytes() for f in sorted((ROOT / "service/vision").rglob("*.py")))
    search = repr(policy).encode()
    return f"{hashlib.sha1(scenes).hexdigest()[:8]}-g{hashlib.sha1(search).hexdigest()[:6]}"


def _record(row: dict) -> PlaneRecord:
    """A kept row (rows kept before the record lost its ``agreement``, the evidence's, carry it too)."""
    return PlaneRecord(row["error_px"], row["reason"], row["evidence"], row["rest"], row.get("scene", -1),
                       row.get("place", -1), row.get("overlap", 0.0))


def plane_calibration(bank: TemplateBank, model: str, mesh_path: Path | None, scenes: int,
                      margin: float = MARGIN, policy: Policy = DEFAULT_POLICY,
                      along: tuple[str, ...] = AGREEMENT_EVIDENCE) -> PlaneCalibration:
    """``bank``'s calibration on ``scenes`` scenes; its records kept under the bank's cache name (a bank
    made without a mesh file, ``mesh_path`` None: under ``model`` and a hash of its vertices)."""
    stem = bank_path(model, mesh_path, None).stem if mesh_path is not None else \
        f"{model}-{hashlib.sha1(bank.vertices_mm.tobytes()).hexdigest()[:12]}"
    name = f"{stem}-{scenes}-{_method(policy)}.jsonl"
    path = OUT_DIR / "plane_calibration" / name
    if path.exists():
        records = [_record(json.loads(s)) for s in path.read_text().splitlines() if s.strip()]
    else:
        t0 = time.perf_counter()
        records = plane_records(bank, scenes, policy=policy)
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text("".join(json.dumps(asdict(r)) + "\n" for r in records))
        print(f"calibrated {model} on {scenes} scenes in {time.perf_counter() - t0:.0f} s", file=sys.stderr)
    return calibrated(records, scenes, margin, along)
