"""``POST /models/{id}/estimate``: one image + intrinsics -> the object's pose (runs in the threadpool)."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, File, Form, UploadFile
from starlette.concurrency import run_in_threadpool

from service import monitoring
from service.api import error_responses
from service.api.bounds import check_plausible
from service.api.deps import Loaded, ReadyModel, SettingsDep, parse_json_part, read_upload
from service.decode import decode_image
from service.pipeline import estimate as estimate_pose
from service.schemas import Camera, EstimateResult, Options
from service.settings import Settings

router = APIRouter(tags=["estimate"])


def run_estimate(model: Loaded, data: bytes, cam: Camera, opts: Options,
                 settings: Settings) -> EstimateResult:
    """Image bytes -> EstimateResult (blocking: call it from a worker thread; the CLI calls it too)."""
    image = decode_image(data, max_pixels=settings.max_image_pixels)
    check_plausible(cam, opts, (image.shape[1], image.shape[0]))
    out = estimate_pose(model.bank, image, cam.to_intrinsics(), distance_mm=opts.distance_mm,
                        distance_range_mm=opts.distance_range_mm, refine=opts.refine, top_k=opts.top_k,
                        overlay=opts.overlay)
    return EstimateResult.from_output(model.id, out)


@router.post("/models/{model_id}/estimate", response_model=EstimateResult,
             responses=error_responses(400, 404, 409, 413, 415, 422))
async def estimate(
    model: ReadyModel,
    settings: SettingsDep,
    image: Annotated[UploadFile, File(description="PNG, JPEG, BMP or TIFF; 8- or 16-bit; grey or colour")],
    camera: Annotated[str, Form(
        description='JSON intrinsics {"fx", "fy", "cx", "cy", optional "dist"}, pixels')],
    options: Annotated[str | None, Form(
        description="JSON: distance_mm or distance_range_mm [min, max], refine, top_k, overlay")] = None,
) -> EstimateResult:
    """Estimate the pose ``T_cam_obj`` of the model in the image."""
    data = await read_upload(image, settings.max_image_bytes, "image file", "POSE_MAX_IMAGE_BYTES")
    cam = parse_json_part(camera, Camera, "camera")
    opts = parse_json_part(options, Options, "options")
    result = await run_in_threadpool(run_estimate, model, data, cam, opts, settings)
    monitoring.observe_estimate(result.timing_ms.model_dump(), result.found)
    return result
