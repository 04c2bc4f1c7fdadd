"""Reference photos: a part's face colours taught from photos at known poses, for the API and the CLI.

An integrator shows the part to the camera at poses it knows (a fixture, a robot holding it, or an
estimate an operator confirmed) and posts each photo with its camera and ``T_cam_obj``
(``POST /models/{id}/references``). The store keeps them (``refs:<id>``, at most ``MAX_REFERENCES``);
``pipeline.teach_appearance`` turns them into the part's ``Appearance`` (``vision/model/appearance.py``),
which every estimate of the model is then judged on too (``verdict.APPEARANCE_WEIGHTS``).

The estimate never teaches on its hot path: ``appearance_of`` keeps each model's taught appearance in a
small per-process memo keyed by the model id and the record's ``references_version``, which the store
renews in the same transaction as every change of the photos, so a photo added or cleared by any
process (one Redis, several replicas) is seen at the next estimate and taught once per process.
A revolved part is taught per ring about its axis, and a plain part's photos are kept but not used
(``pipeline.teach_appearance``, ``Appearance.plain``).

Plain numpy and the service's wire models; no HTTP here (``service.api.references`` is the glue).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import replace
from typing import Any

import numpy as np

from service.bounds import DISTANCE_MM, check_plausible
from service.cell_io import check_image_size
from service.decode import decode_image
from service.errors import NotFoundError, UnprocessableError
from service.form_parts import parse_json_object, validate_part
from service.schemas import CellCamera, Options, Refined, Transform
from service.stores.base import Store, references_full
from service.vision import pipeline
from service.vision.bank import TemplateBank
from service.vision.geometry.camera import Intrinsics, project
from service.vision.geometry.frames import Pose
from service.vision.memo import Memo
from service.vision.model.appearance import Appearance

MAX_REFERENCES = 12  # a few views covering the part's sides teach it; more only fill the store
MIN_IN_IMAGE = 0.5  # share of the part's projected bounding box that must lie inside the photo
MIN_DEPTH_MM = 1.0  # every corner of the part's bounding box must lie this far in front of the camera
TAUGHT_MEMO_SIZE = 16  # models whose taught appearance a process keeps

# The keys an estimate's pose (PoseJSON, Candidate, Refined) has beside R and t_mm: a confirmed estimate's
# ``refined`` pose can be posted back unchanged. Any other unknown key is still refused (a typo).
ESTIMATE_POSE_KEYS = frozenset(Refined.model_fields) - {"R", "t_mm"}

_TAUGHT = Memo(TAUGHT_MEMO_SIZE)
_OWNER = object()  # the memo's one owner: its keys are (model id, references version, faces)


def parse_pose(text: str | None) -> Transform:
    """A ``pose`` form part -> T_cam_obj: ``{"R": 3x3, "t_mm": [x, y, z]}`` (a pose as the estimate
    returns it is accepted too: its other keys are ignored); 422 with one sentence otherwise. R must be
    a rotation within ``cell.ROTATION_ATOL`` and is snapped to the nearest one (a reflection: 422)."""
    value = parse_json_object(text, "pose")
    return validate_part({k: v for k, v in value.items() if k not in ESTIMATE_POSE_KEYS}, Transform, "pose")


def pose_problem(bank: TemplateBank, intr: Intrinsics, pose: Pose, image_size: tuple[int, int]) -> str | None:
    """None when ``pose`` puts the part in front of the camera and mostly inside the (w, h) image;
    else one sentence saying what is wrong and how to fix it."""
    v = np.asarray(bank.vertices_mm, float)
    lo, hi = v.min(axis=0), v.max(axis=0)
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    R, t = np.asarray(pose.R, float), np.asarray(pose.t_mm, float)
    centre = R @ (0.5 * (lo + hi)) + t
    p_cam = corners @ R.T + t
    z = float(centre[2])
    fix = "give T_cam_obj, the part in the camera frame (x right, y down, z along the optical axis, mm)"
    if z <= 0:
        return f"The pose puts the part's centre {-z:.0f} mm behind the camera; {fix}"
    if z > DISTANCE_MM[1]:
        return (f"The pose puts the part's centre {z / 1000:.0f} m from the camera; t_mm is in millimetres: "
                f"{fix}")
    if p_cam[:, 2].min() < MIN_DEPTH_MM:
        size = float(np.linalg.norm(hi - lo))
        return (f"The pose puts the part's centre only {z:.0f} mm in front of the camera, so part of this "
                f"{size:.0f} mm part is behind the lens; t_mm is in millimetres (not metres): {fix}")
    w, h = image_size
    uv = project(p_cam, intr.K)
    (u0, v0), (u1, v1) = uv.min(axis=0), uv.max(axis=0)
    inside_w = max(0.0, min(u1, w - 0.5) - max(u0, -0.5))
    inside_h = max(0.0, min(v1, h - 0.5) - max(v0, -0.5))
    share = inside_w * inside_h / max((u1 - u0) * (v1 - v0), 1e-9)
    if share < MIN_IN_IMAGE:
        uc, vc = project(centre, intr.K)
        return (f"The pose puts the part mostly outside this {w} x {h} image ({100 * share:.0f}% of its "
                f"projected extent inside, its centre at pixel ({uc:.0f}, {vc:.0f})); give the pose the "
                "photo shows the part at, with the intrinsics of this image size")
    return None


def _view(image: np.ndarray, camera: dict[str, Any], T_cam_obj: dict[str, Any]
          ) -> tuple[np.ndarray, Intrinsics, Pose]:
    return (image, CellCamera.model_validate(camera).to_intrinsics(),
            Pose(np.asarray(T_cam_obj["R"], float), np.asarray(T_cam_obj["t_mm"], float)))


def teach_views(bank: TemplateBank, views: list[tuple[np.ndarray, Intrinsics, Pose]]) -> Appearance | None:
    """The appearance reference photos (decoded image, intrinsics, T_cam_obj) teach
    (``pipeline.teach_appearance``: a revolved part's per ring); None for none."""
    if not views:
        return None
    return pipeline.teach_appearance(bank, views)


def stored_views(references: list[dict[str, Any]]) -> list[tuple[np.ndarray, Intrinsics, Pose]]:
    """The stored reference photos (with their image bytes) as views: (decoded image, intrinsics,
    T_cam_obj)."""
    return [_view(decode_image(r["image"]), r["camera"], r["T_cam_obj"]) for r in references]


def teach_stored(bank: TemplateBank, references: list[dict[str, Any]]) -> Appearance | None:
    """The appearance the stored reference photos (with their image bytes) teach; None for none."""
    return teach_views(bank, stored_views(references))


def appearance_of(store: Store, record: dict[str, Any], bank: TemplateBank) -> Appearance | None:
    """The model's taught appearance, None when it has no reference photos: taught once per reference
    set and process (the memo's key, the record's ``references_version``, is new at every change). A set
    changed between reading ``record`` and reading the photos is taught under the older version, which
    only requests still holding the older record ask for. With the record's calibration of this set
    (``calibrate_stored``), the part's operating point is calibrated (``pipeline.operating_point``)."""
    if not record.get("references"):
        return None
    key = (record["id"], record.get("references_version"), len(bank.faces))
    appearance = _TAUGHT.get(_OWNER, key,
                             lambda: teach_stored(bank, store.references(record["id"], images=True)))
    cal = record.get("calibration") or {}
    if appearance is None or cal.get("references_version") != record.get("references_version"):
        return appearance
    wrong = cal.get("wrong_score")
    return replace(appearance, wrong_score=-math.inf if wrong is None else float(wrong),
                   calibrated_photos=int(cal["photos"]))


def calibrate_stored(store: Store, record: dict[str, Any], bank: TemplateBank,
                     progress: Callable[[int, int], None] | None = None) -> dict[str, Any]:
    """The part's operating point calibrated on its stored photos (``pipeline.calibrate_appearance``: each
    searched, taught by the others; seconds a photo, ``progress(done, total)`` told before each) and kept
    in the record as ``calibration``, keyed by the photo set's ``references_version`` (a set changed
    meanwhile is not calibrated by this: its own post calibrates it): the record as it is then. Photos
    that cannot be (plain, disagreeing, or a single one: ``Appearance.calibratable``) are not calibrated."""
    appearance = appearance_of(store, record, bank)
    if appearance is None or not appearance.calibratable:
        return record
    views = stored_views(store.references(record["id"], images=True))
    calibrated = pipeline.calibrate_appearance(bank, views, appearance, progress=progress)
    if calibrated.calibrated_photos == 0:
        return record
    wrong = calibrated.wrong_score
    cal = {"references_version": record.get("references_version"), "photos": calibrated.calibrated_photos,
           "wrong_score": float(wrong) if np.isfinite(wrong) else None}
    current = store.get(record["id"])
    if current is None or current.get("references_version") != cal["references_version"]:
        return current or record
    return store.update(record["id"], calibration=cal) or record


def _holds_calibration(record: dict[str, Any]) -> bool:
    """Whether the record's stored calibration is of its current photo set."""
    return (record.get("calibration") or {}).get("references_version") == record.get("references_version")


def calibration_due(record: dict[str, Any]) -> bool:
    """Whether the record asks for a calibration of its current photo set that it does not hold (the photos
    must still be calibratable: ``calibrate_stored`` judges that)."""
    return bool(record.get("references")) and bool(record.get("calibration_wanted")) \
        and not _holds_calibration(record)


def calibration_state(record: dict[str, Any], appearance: Appearance | None
                      ) -> tuple[str | None, float | None]:
    """(status, progress 0..1 or None) of the part's calibration on its current photos. Status:
    ``calibrated``; ``running`` (``progress``: the share of the photos searched) or ``queued``;
    ``not_requested`` (posted with ``calibrate=false``); ``not_calibratable`` (a single photo, or photos
    plain or disagreeing); None without photos. A calibration interrupted by a stop is ``running`` with the
    progress it had until the next start of the service resumes it."""
    if appearance is None:
        return None, None
    if _holds_calibration(record):
        return "calibrated", 1.0
    if not appearance.calibratable:
        return "not_calibratable", None
    if not record.get("calibration_wanted"):
        return "not_requested", None
    run = record.get("calibration_progress") or {}
    if run.get("references_version") == record.get("references_version") and run.get("total"):
        return "running", float(run["done"]) / float(run["total"])
    return "queued", 0.0


def add_reference(store: Store, record: dict[str, Any], bank: TemplateBank, data: bytes, cam: CellCamera,
                  camera_name: str | None, pose: Transform, *, max_pixels: int,
                  calibrate: bool = True) -> dict[str, Any]:
    """Check, teach and store one reference photo, and mark whether the part's operating point is to be
    calibrated on all of them (``calibrate``: the record's ``calibration_wanted``; the calibration itself
    runs in the background, ``service.jobs.calibrations``):
    ``{"record": the updated record, "appearance": what every photo teaches now, "faces": the number of
    faces this photo alone teaches, "index": its index}``.

    The image is decoded as the estimate decodes it (the same limits: 413 / 415 / 422), the camera held
    to the estimate's checks for its size, and the pose to ``pose_problem`` (422); a photo that teaches
    no face (422) is not stored."""
    mid = record["id"]
    n = int(record.get("references") or 0)
    if n >= MAX_REFERENCES:  # before decoding: the store says so again, atomically
        raise references_full(mid, n, MAX_REFERENCES)
    image = decode_image(data, max_pixels=max_pixels)
    size = (int(image.shape[1]), int(image.shape[0]))
    check_image_size(cam, size, camera_name)
    check_plausible(cam, Options(), size)
    intr, T = cam.to_intrinsics(), Pose(np.asarray(pose.R, float), np.asarray(pose.t_mm, float))
    problem = pose_problem(bank, intr, T, size)
    if problem is not None:
        raise UnprocessableError(problem)
    alone = pipeline.teach_appearance(bank, [(image, intr, T)])  # as shot: the faces the photo shows
    faces = int(np.isfinite(alone.face_bgr[:, 0]).sum())
    if faces == 0:
        raise UnprocessableError("The photo shows none of the part's faces well at this pose (none is in "
                                 "front of the camera on enough pixels, facing it); check that T_cam_obj is "
                                 "the pose the photo shows the part at and that nothing hides the part")
    stored = {"image": data, "camera": cam.model_dump(exclude_none=True), "camera_name": camera_name,
              "T_cam_obj": {"R": pose.R, "t_mm": pose.t_mm}, "width": size[0], "height": size[1]}
    updated = store.add_reference(mid, stored, MAX_REFERENCES)
    if updated is None:
        raise NotFoundError(f"Model '{mid}' was deleted while its reference photo was taught; upload it "
                            "again with POST /models")
    updated = store.update(mid, calibration_wanted=bool(calibrate)) or updated
    return {"record": updated, "appearance": appearance_of(store, updated, bank), "faces": faces,
            "index": int(updated["references"]) - 1}
