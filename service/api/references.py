"""Reference photos: ``POST/GET/DELETE /models/{id}/references``, the part at known poses, from which its
face colours are taught (``service.references``); every estimate of the model is then judged on them."""

from __future__ import annotations

from typing import Annotated

import numpy as np
from fastapi import APIRouter, File, Form, Response, UploadFile
from starlette.concurrency import run_in_threadpool

from service.api import error_responses
from service.api.deps import CalibratorDep, ModelRecord, ReadyModel, SettingsDep, StoreDep, read_upload
from service.cell_io import resolve_camera, snap_warnings
from service.reference_schemas import ReferenceAdded, ReferencePhoto, References
from service.references import (
    MAX_REFERENCES,
    add_reference,
    appearance_of,
    calibration_state,
    parse_pose,
)
from service.vision.estimate.verdict import MIN_SCORE
from service.vision.pipeline import operating_point

router = APIRouter(tags=["models"])


@router.post("/models/{model_id}/references", status_code=201, response_model=ReferenceAdded,
             responses=error_responses(400, 404, 409, 413, 415, 422))
async def post_reference(
    model: ReadyModel,
    settings: SettingsDep,
    store: StoreDep,
    calibrator: CalibratorDep,
    response: Response,
    image: Annotated[UploadFile, File(
        description="the part alone, unoccluded, in the cell's light: PNG, JPEG, BMP or TIFF")],
    camera: Annotated[str, Form(
        description='JSON intrinsics as the estimate takes them {"fx", "fy", "cx", "cy", optional "dist", '
                    '"width", "height", ...}, pixels; or {"name": "<registered camera>"}')],
    pose: Annotated[str, Form(
        description='JSON T_cam_obj, the part\'s pose in this photo: {"R": 3x3 row-major, "t_mm": [x, y, z]} '
                    "(a pose as the estimate returns it is accepted unchanged)")],
    calibrate: Annotated[bool, Form(
        description="calibrate the part's operating point on all the stored photos after this one, in the "
                    "background (seconds a photo); false to post several photos and calibrate with the last")
    ] = True,
    wait: Annotated[bool, Form(
        description="answer only once this process has calibrated the photos (seconds a stored photo); by "
                    "default the answer comes at once and GET shows the calibration's progress")] = False,
) -> ReferenceAdded:
    """Add a reference photo of the part at a known pose, teach its colours from all of them and, once
    they are used, calibrate the part's operating point on them in the background (seconds a stored photo:
    each is searched as a frame); at most ``max_references``; DELETE them to start again."""
    data = await read_upload(image, settings.max_image_bytes, "image file", "POSE_MAX_IMAGE_BYTES")
    cam, camera_name = resolve_camera(camera, store)
    T_cam_obj = parse_pose(pose)
    out = await run_in_threadpool(add_reference, store, model.record, model.bank, data, cam, camera_name,
                                  T_cam_obj, max_pixels=settings.max_image_pixels, calibrate=calibrate)
    record = out["record"]
    if calibrate:
        calibrator.submit(model.id)
        if wait:
            await run_in_threadpool(calibrator.wait, model.id)
            record = store.get(model.id) or record
    appearance = appearance_of(store, record, model.bank)
    response.headers["Location"] = f"/models/{model.id}/references"
    return ReferenceAdded(model_id=model.id, index=out["index"], references=record["references"],
                          max_references=MAX_REFERENCES, known_fraction=appearance.known_fraction,
                          faces_taught_by_this_view=out["faces"], **_judged(record, appearance),
                          warnings=[w for w in [T_cam_obj.snap_warning("pose")] if w] + snap_warnings(cam))


@router.get("/models/{model_id}/references", response_model=References, responses=error_responses(404, 422))
def get_references(record: ModelRecord, store: StoreDep) -> References:
    """The model's reference photos (without their images) and how much of the part they teach."""
    views = store.references(record["id"])
    known, appearance = None, None
    if record.get("status") == "ready" and (bank := store.bank(record["id"])) is not None:
        appearance = appearance_of(store, record, bank)
        known = 0.0 if appearance is None else appearance.known_fraction
    taught = {} if appearance is None else _judged(record, appearance)
    return References(model_id=record["id"], references=len(views), max_references=MAX_REFERENCES,
                      known_fraction=known, **taught,
                      views=[ReferencePhoto(index=i, **v) for i, v in enumerate(views)])


@router.delete("/models/{model_id}/references", status_code=204, response_class=Response,
               responses=error_responses(404, 422))
def delete_references(record: ModelRecord, store: StoreDep) -> Response:
    """Remove every reference photo: the part is judged as untaught again."""
    store.clear_references(record["id"])
    return Response(status_code=204)


def _judged(record: dict, appearance) -> dict:
    """What decides whether estimates use the taught colours (NaN, e.g. one photo's agreement: null), and
    how far their calibration is."""
    agreement, wrong = appearance.agreement, appearance.wrong_score
    status, progress = calibration_state(record, appearance)
    return {"plain": appearance.plain, "reference_shading_r2": appearance.reference_shading_r2,
            "hue_share": appearance.hue_share, "used": appearance.used,
            "agreement": None if not np.isfinite(agreement) else agreement,
            "calibrated": appearance.calibrated_photos > 0,
            "calibration_wrong_score": float(wrong) if np.isfinite(wrong) else None,
            "min_score": (operating_point(appearance) or MIN_SCORE) if appearance.used else None,
            "calibration_status": status, "calibration_progress": progress}
