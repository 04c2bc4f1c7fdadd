"""Models: upload a mesh (its templates build in the background), list, inspect, delete, picture."""

from __future__ import annotations

from typing import Annotated

import cv2
from fastapi import APIRouter, File, Form, Response, UploadFile
from starlette.concurrency import run_in_threadpool

from service.api import error_responses
from service.api.deps import (
    BuilderDep,
    CalibratorDep,
    ModelRecord,
    ReadyModel,
    SettingsDep,
    StoreDep,
    read_upload,
)
from service.errors import NotFoundError
from service.form_parts import parse_json_object
from service.jobs.build import register_upload
from service.schemas import ModelInfo, SymmetryOption, Units
from service.vision.pipeline import template_picture

router = APIRouter(tags=["models"])
NAME_MAX_CHARS = 200


@router.post("/models", status_code=202, response_model=ModelInfo,
             responses=error_responses(400, 413, 415, 422))
async def upload_model(
    response: Response,
    store: StoreDep,
    settings: SettingsDep,
    builder: BuilderDep,
    file: Annotated[UploadFile, File(
        description="the CAD mesh: STL (binary or ASCII), OBJ, PLY, OFF or GLB")],
    name: Annotated[str | None, Form(description="a label; defaults to the file name",
                                     max_length=NAME_MAX_CHARS)] = None,
    units: Annotated[Units, Form(description="the mesh's unit, converted to mm once")] = "mm",
    symmetry: Annotated[SymmetryOption, Form(
        description="auto (detect), none, or the model-frame axis x, y, z of a continuous symmetry",
    )] = "auto",
    templates: Annotated[str | None, Form(
        description="JSON object of template-grid options (steps and ranges in degrees)")] = None,
) -> ModelInfo:
    """Register a mesh and start building its templates; the same bytes and options give the same id."""
    data = await _read_mesh(file, settings.max_mesh_bytes)
    grid = parse_json_object(templates, "templates")
    record, needs_build = await run_in_threadpool(
        register_upload, store, settings, data, filename=file.filename or "", name=name or None, units=units,
        symmetry=symmetry, templates=grid)
    if needs_build:
        builder.submit(record["id"])
    response.headers["Location"] = f"/models/{record['id']}"
    return ModelInfo.from_record(record)


async def _read_mesh(file: UploadFile, limit: int) -> bytes:
    """The mesh file's bytes (413 over ``limit``). With the size the multipart parser counted, one read
    into one buffer: ``read_upload``'s 1 MB chunks come from the heap, which keeps freed memory mapped
    for the estimates (``vision.memory``), so a 100 MB upload kept ~95 MB resident after its model
    was deleted; a buffer this large is a mapping of its own, returned when it is freed."""
    if file.size is None or file.size > limit:
        return await read_upload(file, limit, "mesh file", "POSE_MAX_MESH_BYTES")
    data = await file.read()
    if len(data) > limit:  # more than was counted: read again the way that stops at the limit
        await file.seek(0)
        return await read_upload(file, limit, "mesh file", "POSE_MAX_MESH_BYTES")
    return data


@router.get("/models", response_model=list[ModelInfo])
def list_models(store: StoreDep, settings: SettingsDep, calibrator: CalibratorDep) -> list[ModelInfo]:
    records = store.records()
    for r in records:
        calibrator.submit_plane(r)
    return [ModelInfo.from_record(r, settings.plane_calibration_scenes) for r in records]


@router.get("/models/{model_id}", response_model=ModelInfo, responses=error_responses(404, 422))
def get_model(record: ModelRecord, settings: SettingsDep, calibrator: CalibratorDep) -> ModelInfo:
    """The model's record; a ready part's plane calibration, if due, is queued (``submit_plane``)."""
    calibrator.submit_plane(record)
    return ModelInfo.from_record(record, settings.plane_calibration_scenes)


@router.delete("/models/{model_id}", status_code=204, response_class=Response,
               responses=error_responses(404, 422))
def delete_model(record: ModelRecord, store: StoreDep, builder: BuilderDep) -> Response:
    store.delete(record["id"])
    builder.cancel(record["id"])  # a build of it here ends now; one in another process within WATCH_S
    return Response(status_code=204)


@router.get("/models/{model_id}/templates/{k}.png", response_class=Response,
            responses={200: {"content": {"image/png": {}}, "description": "template k: projected mesh | "
                             "extracted borderline"}, **error_responses(404, 409, 422)})
def template_png(model: ReadyModel, k: int) -> Response:
    """Template ``k`` drawn for a person: the projected mesh and its extracted borderline side by side."""
    n = model.bank.n_templates
    if not 0 <= k < n:
        raise NotFoundError(f"Model '{model.id}' has templates 0 to {n - 1}, not {k}; ask for one in that "
                            "range")
    ok, png = cv2.imencode(".png", template_picture(model.bank, k))
    if not ok:
        raise RuntimeError(f"PNG encoding of template {k} failed")
    return Response(png.tobytes(), media_type="image/png")
