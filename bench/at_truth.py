"""What the plane verdict reads at the truth: each target copy's material-free agreement at its ground-truth
pose against its part's calibrated point (at the copy's resting family), so a set's losses split into those
a perfect search and refinement would recover (the truth reads over its point) and those the verdict
itself refuses (the truth reads under it, or its outline is a plain shape's).

With ``--records`` (a ``bench/cell.py --json`` file of the same set) each target is also counted as the
run left it: found right, checked within 20 px, or not reached.

    NUMBA_NUM_THREADS=1 python bench/at_truth.py --sets sygrid_synth [--stride 4] [--records run.jsonl]
"""

from __future__ import annotations

import argparse
import json
import sys
from collections import defaultdict
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from bench.cell import MIN_VISIBLE, plane_of, queries_of  # noqa: E402
from bench.lib.calibration import plane_calibration  # noqa: E402
from bench.lib.data import PART_NAMES, gt_bank, read_colour, read_gt, set_dir_of  # noqa: E402
from service.vision.estimate.edge_agreement import edge_agreement  # noqa: E402
from service.vision.estimate.evidence import colour_frame, evidence  # noqa: E402
from service.vision.estimate.verdict import AGREEMENT_EVIDENCE, distinct, material_free  # noqa: E402
from service.vision.geometry.camera import Intrinsics  # noqa: E402
from service.vision.geometry.frames import Pose  # noqa: E402
from service.vision.pipeline.part import crease_edges_of, rest_family  # noqa: E402
from service.vision.pipeline.plane_calibration import SCENES  # noqa: E402

KEPT_EVIDENCE = (*AGREEMENT_EVIDENCE, "polarity", "distinct_px")  # each row's, for reading other points


def truth_reads(name: str, *, stride: int = 1, min_visible: float = MIN_VISIBLE) -> list[dict]:
    """One row per target copy: its part, image, visible share, agreement at the truth, point, distinct."""
    set_dir = set_dir_of(name)
    gts = read_gt(set_dir)
    banks, cal, rows = {}, {}, []
    for image, model, lines in queries_of(gts, stride=stride):
        copies = [g for g in lines if not g.get("absent", False)]
        if not copies:
            continue
        if model not in banks:
            banks[model] = gt_bank(set_dir, model)
            cal[model] = plane_calibration(banks[model], model, set_dir / "models" / f"{model}.stl", SCENES)
        bank, c = banks[model], cal[model]
        plane = plane_of(copies[0])
        frame = colour_frame(read_colour(set_dir / image))
        intr = Intrinsics.from_K(np.asarray(copies[0]["K"], float))
        for k, g in enumerate(copies):
            if float(g.get("visible_fraction", 1.0)) < min_visible:
                continue
            pose = Pose(np.asarray(g["R"], float), np.asarray(g["t_mm"], float))
            ev = evidence(bank, pose, intr, frame).as_dict()
            ev |= edge_agreement(bank.vertices_mm, bank.faces, crease_edges_of(bank), pose, intr,
                                 frame.agreeing)
            rest = rest_family(bank, pose.R, plane.normal)
            rows.append({"model": model, "image": image, "copy": k,
                         "visible": float(g.get("visible_fraction", 1.0)),
                         "agreement": material_free(ev, c.agreement_along),
                         "point": c.agreement.at_rest(rest).point, "distinct": distinct(ev),
                         "along": c.agreement_along, "rest": rest,
                         "evidence": {e: float(ev[e]) for e in KEPT_EVIDENCE}})
    return rows


def run_states(path: Path) -> dict:
    """(image, model, copy) -> "found" / "checked" / "missed" from a ``bench/cell.py --json`` file."""
    out = {}
    for line in path.read_text().splitlines():
        r = json.loads(line)
        for k, c in enumerate(r["copies"]):
            state = "found" if c["right"] else "checked" if c["proposed"] else "missed"
            out[(r["image"], r["model"], k)] = state
    return out


def table(rows: list[dict], states: dict | None) -> str:
    head = ["part", "targets", "plain outline", "not calibrated", "truth over its point",
            "truth median - point"]
    if states is not None:
        head += ["found", "over, checked not found", "over, not reached"]
    out = ["| " + " | ".join(head) + " |", "|---" * len(head) + "|"]
    by = defaultdict(list)
    for r in rows:
        by[PART_NAMES.get(r["model"], r["model"])].append(r)
    for part in [*sorted(by), "**all**"]:
        rs = rows if part == "**all**" else by[part]
        calibrated = [r for r in rs if r["point"] is not None and r["distinct"]]
        over = [r for r in calibrated if r["agreement"] >= r["point"]]
        gap = np.median([r["agreement"] - r["point"] for r in calibrated]) if calibrated else float("nan")
        cells = [part, str(len(rs)), str(sum(not r["distinct"] for r in rs)),
                 str(sum(r["point"] is None for r in rs)), f"{len(over)} ({len(over) / len(rs):.0%})",
                 f"{gap:+.3f}"]
        if states is not None:
            st = [states.get((r["image"], r["model"], r["copy"]), "missed") for r in rs]
            ov = [states.get((r["image"], r["model"], r["copy"]), "missed") for r in over]
            cells += [str(st.count("found")), str(ov.count("checked")), str(ov.count("missed"))]
        out.append("| " + " | ".join(cells) + " |")
    return "\n".join(out)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sets", default="sygrid_synth")
    ap.add_argument("--stride", type=int, default=1)
    ap.add_argument("--records", type=Path, default=None, help="bench/cell.py --json of the same set")
    ap.add_argument("--json", type=Path, default=None, help="one JSON line per target")
    args = ap.parse_args(argv)
    for name in args.sets.split(","):
        rows = truth_reads(name, stride=args.stride)
        if args.json is not None:
            args.json.write_text("".join(json.dumps(r) + "\n" for r in rows))
        print(f"\n{Path(name).name}\n")
        print(table(rows, run_states(args.records) if args.records is not None else None))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
