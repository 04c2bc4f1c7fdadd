"""``POST /models/{id}/estimate``: one image + intrinsics -> the object's pose (runs in the threadpool)."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, File, Form, UploadFile
from starlette.concurrency import run_in_threadpool

from service import monitoring
from service.api import error_responses
from service.api.deps import CalibratorDep, Loaded, ReadyModel, SettingsDep, StoreDep, read_upload
from service.cell import Grasp
from service.cell_io import check_robot_pose, estimate_options, estimate_result, grasps_of, resolve_camera
from service.references import appearance_of
from service.schemas import Camera, EstimateResult, Options
from service.settings import Settings
from service.stores.base import Store

router = APIRouter(tags=["estimate"])


def run_estimate(model: Loaded, data: bytes, cam: Camera, opts: Options, settings: Settings, store: Store, *,
                 camera_name: str | None = None, grasps: list[Grasp] | None = None) -> EstimateResult:
    """Image bytes -> EstimateResult (blocking: call it from a worker thread). A model with reference
    photos is judged on its taught colours too (taught once per set of photos: ``appearance_of``)."""
    return estimate_result(model.record, model.bank, data, cam, opts, max_pixels=settings.max_image_pixels,
                           camera_name=camera_name, grasps=grasps, default_deadline_ms=settings.deadline_ms,
                           appearance=appearance_of(store, model.record, model.bank))


@router.post("/models/{model_id}/estimate", response_model=EstimateResult,
             responses=error_responses(400, 404, 409, 413, 415, 422))
async def estimate(
    model: ReadyModel,
    settings: SettingsDep,
    store: StoreDep,
    calibrator: CalibratorDep,
    image: Annotated[UploadFile, File(description="PNG, JPEG, BMP or TIFF; 8- or 16-bit; grey or colour")],
    camera: Annotated[str, Form(
        description='JSON intrinsics {"fx", "fy", "cx", "cy", optional "dist", "width", "height", '
                    '"T_base_cam" or "T_flange_cam"}, pixels and mm; or {"name": "<registered camera>"}')],
    options: Annotated[str | None, Form(
        description="JSON: distance_mm or distance_range_mm [min, max], refine, top_k, overlay, min_score, "
                    "robot_pose (T_base_flange, eye-in-hand), roi, max_instances, sort (score | distance | "
                    'height), plane {"normal": [nx, ny, nz], "d_mm": d} (camera frame, normal towards the '
                    "camera), plane_tolerance_mm, deadline_ms (see docs/API.md)")] = None,
) -> EstimateResult:
    """Estimate the pose ``T_cam_obj`` of the model in the image."""
    data = await read_upload(image, settings.max_image_bytes, "image file", "POSE_MAX_IMAGE_BYTES")
    cam, camera_name = resolve_camera(camera, store)
    opts = estimate_options(options, cam, camera_name, store)
    check_robot_pose(cam, opts, camera_name)
    if opts.plane is not None:  # a part estimated on a plane is calibrated for one, if it is not yet
        calibrator.submit_plane(model.record)
    grasps = grasps_of(store.grasps(model.id))
    result = await run_in_threadpool(run_estimate, model, data, cam, opts, settings, store,
                                     camera_name=camera_name, grasps=grasps)
    monitoring.observe_estimate(result.timing_ms.model_dump(), result.found)
    return result
