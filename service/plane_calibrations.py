"""A part's plane calibration (``vision/pipeline/plane_calibration.py``) kept in its record.

Once a part's templates are ready, the process's ``Calibrator`` renders scenes of it among look-alike
shapes and sets the agreement of visible edges a pose on a plane must reach (about a minute a part). The
record holds it as ``plane_calibration``::

    {"version": 3, "status": "running", "done": 3, "total": 12}
    {"version": 3, "status": "calibrated", "agreement_min": 0.71, "agreement_floor": 0.3,
     "agreement_along": "outline_agreement", "scenes": 12, ...}

A calibration of an older method (``version``), or one a stop or a crash ended, is due again: every
start-up re-queues it. Until a part is calibrated, a request on a plane judges it on the material-bound
score alone, and says so in its warnings.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING, Any

from service.vision.bank import TemplateBank
from service.vision.estimate.verdict import PlaneAgreement
from service.vision.pipeline.plane_calibration import calibrate_plane

if TYPE_CHECKING:
    from service.stores.base import Store

# The calibration's method: a calibration of another is made again.
VERSION = 9
KEY = "plane_calibration"


def plane_calibration_due(record: dict[str, Any], scenes: int) -> bool:
    """Whether the record's part is ready and lacks a calibration of this method that ended (calibrated,
    or failed: it would fail again)."""
    cal = record.get(KEY) or {}
    return (scenes > 0 and record.get("status") == "ready"
            and not (cal.get("version") == VERSION and cal.get("status") in ("calibrated", "failed")))


def plane_calibration_failed(store: Store, mid: str, error: str) -> None:
    """Keep in record ``mid`` that its calibration failed (``error``: why), so it is not tried again."""
    store.update(mid, **{KEY: {"version": VERSION, "status": "failed", "error": error}})


def agreement_min_of(record: dict[str, Any]) -> float | None:
    """The agreement a pose of the part on a plane must reach; None until calibrated (or not calibratable)."""
    return _calibrated_value(record, "agreement_min")


def agreement_floor_of(record: dict[str, Any]) -> float | None:
    """The least agreement a pose of the part on a plane is found with; None until calibrated."""
    return _calibrated_value(record, "agreement_floor")


def agreement_min_by_rest_of(record: dict[str, Any]) -> tuple[float | None, ...]:
    """Each resting family's agreement to reach (None: ``agreement_min``); empty until calibrated."""
    kept = (_calibrated(record) or {}).get("agreement_min_by_rest") or ()
    return tuple(None if a is None else float(a) for a in kept)


def agreement_min_place_of(record: dict[str, Any]) -> float | None:
    """The agreement a pose no other candidate at its place outagrees must reach; None: none."""
    return _calibrated_value(record, "agreement_min_place")


def agreement_along_of(record: dict[str, Any]) -> str | None:
    """Along which edges the part's agreement is read (``verdict.AGREEMENT_EVIDENCE``); None until
    calibrated."""
    cal = _calibrated(record)
    return None if cal is None else str(cal.get("agreement_along", "edge_agreement"))


def plane_agreement_of(record: dict[str, Any]) -> PlaneAgreement | None:
    """The part's operating point on a plane as the verdict takes it; None until calibrated."""
    along = agreement_along_of(record)
    if along is None:
        return None
    return PlaneAgreement(agreement_min_of(record), agreement_floor_of(record), along,
                          agreement_min_by_rest_of(record), agreement_min_place_of(record))


def _calibrated(record: dict[str, Any]) -> dict[str, Any] | None:
    """The record's calibration if it is of this method and ended calibrated, else None."""
    cal = record.get(KEY) or {}
    return cal if cal.get("version") == VERSION and cal.get("status") == "calibrated" else None


def _calibrated_value(record: dict[str, Any], key: str) -> float | None:
    a = (_calibrated(record) or {}).get(key)
    return None if a is None else float(a)


def plane_calibration_warning(record: dict[str, Any]) -> str | None:
    """A request's warning when the part on a plane is not judged on its visible edges' agreement."""
    cal = record.get(KEY) or {}
    if agreement_min_of(record) is not None:
        return None
    if cal.get("version") == VERSION and cal.get("status") == "failed":
        return (f"The part's plane calibration failed ({cal.get('error')}): on a plane it is judged on "
                "shading and region alone, which miss most shiny or plastic parts")
    if cal.get("version") == VERSION and cal.get("status") == "calibrated":
        return ("The part's plane calibration found no agreement that keeps wrong poses out (its shape is "
                "too plain among look-alikes): on a plane it is judged on shading and region alone, which "
                "miss most shiny or plastic parts; teach it from reference photos")
    done, total = int(cal.get("done") or 0), int(cal.get("total") or 0)
    state = f"running ({done} of {total} scenes)" if cal.get("status") == "running" else "not done"
    return (f"The part's plane calibration is {state}: until it is, parts on a plane are judged on shading "
            "and region alone, which miss most shiny or plastic parts; GET /models/{id} shows its progress "
            "(none runs with POSE_PLANE_CALIBRATION_SCENES=0)")


def plane_calibration_info(record: dict[str, Any], scenes: int | None) -> dict[str, Any] | None:
    """What ``GET /models/{id}`` shows of it (null before the part is ready). ``scenes``: the service's
    ``plane_calibration_scenes`` (0: none is made; None: not known here)."""
    if record.get("status") != "ready":
        return None
    cal = record.get(KEY) or {}
    current = cal.get("version") == VERSION
    status = cal.get("status") if current else ("not_requested" if scenes == 0 else "queued")
    total = int(cal.get("total") or cal.get("scenes") or 0)
    progress = 1.0 if status == "calibrated" else (int(cal.get("done") or 0) / total if total else 0.0)
    return {"status": status, "progress": progress,
            "agreement_min": agreement_min_of(record),
            "agreement_floor": agreement_floor_of(record),
            "agreement_along": agreement_along_of(record),
            "agreement_min_by_rest": list(agreement_min_by_rest_of(record))
            if status == "calibrated" else None,
            "agreement_min_place": agreement_min_place_of(record),
            "wrong_max": cal.get("wrong_max") if current else None,
            "scenes": int(cal.get("scenes") or 0) if status == "calibrated" else None,
            "error": cal.get("error") if status == "failed" else None}


def calibrate_plane_stored(store: Store, mid: str, bank: TemplateBank, scenes: int,
                           progress: Callable[[int, int], None] | None = None) -> dict[str, Any] | None:
    """``bank``'s part calibrated on ``scenes`` rendered scenes, kept in record ``mid``: the record then
    (None if it was deleted). ``progress(done, total)`` is told before each scene and may raise to stop."""

    def told(done: int, total: int) -> None:
        if progress is not None:
            progress(done, total)
        store.update(mid, **{KEY: {"version": VERSION, "status": "running", "done": done, "total": total}})

    cal = calibrate_plane(bank, scenes, progress=told)
    kept = {"version": VERSION, "status": "calibrated", "agreement_min": cal.agreement_min,
            "agreement_floor": cal.agreement_floor, "agreement_along": cal.agreement_along,
            "agreement_min_by_rest": list(cal.agreement_min_by_rest),
            "agreement_min_place": cal.agreement_min_place,
            "wrong_max": float(cal.wrong_max), "right": cal.right, "right_total": cal.right_total,
            "wrong_total": cal.wrong_total, "scenes": cal.scenes}
    return store.update(mid, **{KEY: kept})
