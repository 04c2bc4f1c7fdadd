"""Cameras: ``PUT/GET/DELETE /cameras/{name}`` (intrinsics, image size, extrinsics, plane), and the
estimate's side of them: a ``camera`` part that names one, the image-size check, robot-frame poses
and grasps added to a result (``service.cell`` does the frame math)."""

from __future__ import annotations

from typing import Annotated, Any

import numpy as np
from fastapi import APIRouter, Path, Response

from service.api import error_responses
from service.api.deps import StoreDep, parse_json_object, parse_json_part
from service.cell import Grasp, base_from_cam, place_grasps, rigid
from service.errors import NotFoundError, UnprocessableError
from service.schemas import (
    CAMERA_NAME_PATTERN,
    CameraInfo,
    CameraRef,
    CameraSpec,
    CellCamera,
    EstimateResult,
    FramePose,
    GraspSpec,
    Options,
    PlacedGraspJSON,
)
from service.vision.bank import TemplateBank

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
    return _info(name, camera.model_dump())


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


# --- the estimate's side ------------------------------------------------------------------------------

def resolve_camera(text: str | None, store) -> tuple[CellCamera, str | None]:
    """An estimate's ``camera`` part -> (the camera, its registered name or None): inline intrinsics,
    or ``{"name": "<registered>"}``; 422 for an unknown name."""
    value = parse_json_object(text, "camera")
    if "name" not in value:
        return parse_json_part(text, CellCamera, "camera"), None
    if len(value) > 1:
        others = ", ".join(sorted(k for k in value if k != "name"))
        raise UnprocessableError(f"The camera part names a registered camera and also has {others}; send "
                                 "either {\"name\": \"<registered>\"} alone or the intrinsics inline "
                                 "without a name")
    ref = parse_json_part(text, CameraRef, "camera")
    record = store.camera(ref.name)
    if record is None:
        raise UnprocessableError(f"No camera is registered as '{ref.name}'; register it with PUT /cameras/"
                                 f"{ref.name}, list the registered ones with GET /cameras, or send the "
                                 "intrinsics inline")
    fields = {k: v for k, v in record.items() if k in CellCamera.model_fields}
    return CellCamera.model_validate(fields), ref.name


def check_robot_pose(cam: CellCamera, opts: Options, name: str | None) -> None:
    """422 when an eye-in-hand camera comes without the shot's robot pose."""
    if cam.T_flange_cam is not None and opts.robot_pose is None:
        which = f"Camera '{name}'" if name else "The camera"
        raise UnprocessableError(
            f"{which} is mounted on the robot's flange (T_flange_cam, eye-in-hand), so every estimate needs "
            "options.robot_pose: send T_base_flange, the flange pose when the image was taken, as "
            "{\"R\": 3x3, \"t_mm\": [x, y, z]}")


def check_image_size(cam: CellCamera, image_size: tuple[int, int], name: str | None) -> None:
    """422 when the image is not the size the camera's intrinsics belong to (``image_size`` = (w, h))."""
    if cam.width is None or cam.height is None:
        return
    w, h = image_size
    if (w, h) != (cam.width, cam.height):
        which = f"camera '{name}' is registered for" if name else "the camera part's width and height say"
        raise UnprocessableError(
            f"The image is {w}x{h} pixels but {which} {cam.width}x{cam.height}; send the camera's full, "
            "unscaled frames, or register the camera again with the intrinsics of this image size")


def grasps_of(records: list[dict[str, Any]]) -> list[Grasp]:
    specs = [GraspSpec.model_validate(r) for r in records]
    return [Grasp(s.name, s.T_obj_grasp.matrix(), np.asarray(s.approach_axis, float)) for s in specs]


def add_cell_frames(result: EstimateResult, bank: TemplateBank, cam: CellCamera, opts: Options,
                    grasps: list[Grasp], camera_name: str | None = None) -> EstimateResult:
    """The result with ``T_base_obj`` on every pose (when the extrinsics are known) and the grasps of
    the reported pose (the refined one, else the coarse one; none when not found)."""
    T_base_cam = base_from_cam(
        None if cam.T_base_cam is None else cam.T_base_cam.matrix(),
        None if cam.T_flange_cam is None else cam.T_flange_cam.matrix(),
        None if opts.robot_pose is None else opts.robot_pose.matrix())
    result.camera_name = camera_name
    if T_base_cam is not None:
        for pose in [result.coarse, result.refined, *result.candidates]:
            if pose is not None:
                pose.T_base_obj = FramePose.from_matrix(T_base_cam @ rigid(pose.R, pose.t_mm))
    reported = result.refined or result.coarse
    if result.found and reported is not None and grasps:
        placed = place_grasps(rigid(reported.R, reported.t_mm), grasps, T_base_cam,
                              symmetry_axis_obj=bank.symmetry_axis_obj,
                              symmetry_point_obj=bank.symmetry_point_obj)
        result.grasps = [PlacedGraspJSON(
            name=p.name, T_cam_grasp=FramePose.from_matrix(p.T_cam_grasp),
            T_base_grasp=None if p.T_base_grasp is None else FramePose.from_matrix(p.T_base_grasp),
            approach_angle_deg=p.approach_angle_deg, spin_deg=p.spin_deg) for p in placed]
    return result
