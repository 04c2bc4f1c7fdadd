"""A part's plane calibration (``pipeline/plane_calibration``) as the service makes it at upload, its
records kept in bench/out/plane_calibration/ per (bank, scenes) and made again only when missing."""

from __future__ import annotations

import json
import sys
import time
from dataclasses import asdict
from pathlib import Path

from bench.lib.data import OUT_DIR, bank_path
from service.vision.bank import TemplateBank
from service.vision.pipeline.plane_calibration import (
    MARGIN,
    PlaneCalibration,
    PlaneRecord,
    calibrated,
    plane_records,
)


def plane_calibration(bank: TemplateBank, model: str, mesh_path: Path, scenes: int,
                      margin: float = MARGIN) -> PlaneCalibration:
    path = OUT_DIR / "plane_calibration" / f"{bank_path(model, mesh_path, None).stem}-{scenes}.jsonl"
    if path.exists():
        records = [PlaneRecord(**json.loads(s)) for s in path.read_text().splitlines() if s.strip()]
    else:
        t0 = time.perf_counter()
        records = plane_records(bank, scenes)
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text("".join(json.dumps(asdict(r)) + "\n" for r in records))
        print(f"calibrated {model} on {scenes} scenes in {time.perf_counter() - t0:.0f} s", file=sys.stderr)
    return calibrated(records, scenes, margin)
