"""Cameras: ``PUT/GET/DELETE /cameras/{name}`` (intrinsics, image size, extrinsics, plane). The
estimate's side of them (a ``camera`` part that names one, the checks, robot-frame poses and grasps)
is ``service.cell_io``, which the CLI calls too."""

from __future__ import annotations

from typing import Annotated, Any

from fastapi import APIRouter, Path, Response

from service.api import error_responses
from service.api.deps import StoreDep
from service.cell_io import snap_warnings
from service.errors import NotFoundError
from service.schemas import (
    CAMERA_NAME_PATTERN,
    CameraInfo,
    CameraSpec,
)

router = APIRouter(tags=["cameras"])

CameraName = Annotated[str, Path(
    pattern=CAMERA_NAME_PATTERN,
    description="1-64 letters, digits, '_', '.', '-' (starting with a letter or digit)")]


def _info(name: str, record: dict[str, Any]) -> CameraInfo:
    spec = CameraSpec.model_validate(record)
    return CameraInfo(**spec.model_dump(), name=name, mounting=spec.mounting_kind())


def _missing(name: str) -> NotFoundError:
    return NotFoundError(f"No camera is registered as '{name}'; list the cameras with GET /cameras or "
                         f"register it with PUT /cameras/{name}")


@router.put("/cameras/{name}", response_model=CameraInfo,
            responses={201: {"model": CameraInfo, "description": "Camera registered."},
                       200: {"description": "Camera replaced."}, **error_responses(422)})
def put_camera(name: CameraName, camera: CameraSpec, store: StoreDep, response: Response) -> CameraInfo:
    """Register (201) or replace (200) a camera: intrinsics, the image size it sends, optionally its
    extrinsics (``T_base_cam`` eye-to-hand or ``T_flange_cam`` eye-in-hand) and a supporting plane."""
    created = store.put_camera(name, camera.model_dump())
    response.status_code = 201 if created else 200
    if created:
        response.headers["Location"] = f"/cameras/{name}"
    info = _info(name, camera.model_dump())
    info.warnings = snap_warnings(camera)  # the stored R is the snapped one: only this answer can say so
    return info


@router.get("/cameras", response_model=list[CameraInfo])
def list_cameras(store: StoreDep) -> list[CameraInfo]:
    return [_info(name, record) for name, record in store.cameras()]


@router.get("/cameras/{name}", response_model=CameraInfo, responses=error_responses(404, 422))
def get_camera(name: CameraName, store: StoreDep) -> CameraInfo:
    record = store.camera(name)
    if record is None:
        raise _missing(name)
    return _info(name, record)


@router.delete("/cameras/{name}", status_code=204, response_class=Response,
               responses=error_responses(404, 422))
def delete_camera(name: CameraName, store: StoreDep) -> Response:
    if not store.delete_camera(name):
        raise _missing(name)
    return Response(status_code=204)
