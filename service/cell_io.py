"""The estimate's side of the cell, for the API and the CLI alike: a ``camera`` part that names a
registered camera, the image-size and robot-pose checks, and the robot-frame poses and placed grasps
added to a result (``service.cell`` does the frame math); ``estimate_result`` runs one estimate."""

from __future__ import annotations

import time
from typing import Any

import numpy as np

from service.bounds import check_apparent_size, check_plausible
from service.cell import Grasp, base_from_cam, place_grasps, rigid
from service.decode import decode_image, image_size
from service.errors import UnprocessableError
from service.form_parts import parse_json_object, parse_json_part, validate_part
from service.plane_calibrations import plane_agreement_of, plane_calibration_warning
from service.schemas import (
    Camera,
    CameraRef,
    CellCamera,
    EstimateResult,
    FramePose,
    GraspSpec,
    ModelInfo,
    Options,
    PlacedGraspJSON,
    PoseJSON,
)
from service.vision.bank import TemplateBank
from service.vision.model.appearance import Appearance
from service.vision.pipeline import estimate_image


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


def estimate_options(text: str | None, cam: CellCamera, camera_name: str | None, store) -> Options:
    """An estimate's ``options`` part -> Options, with a registered fixed camera's plane as the default
    ``plane``: it applies when the options name neither ``plane`` (``"plane": null`` opts out) nor
    ``distance_mm`` (which a plane excludes). An eye-in-hand camera's plane moves with the flange, so
    it is never a default."""
    value = parse_json_object(text, "options")
    plane = registered_plane(cam, camera_name, store)
    if plane is not None and "plane" not in value and value.get("distance_mm") is None:
        value = {**value, "plane": plane}
    return validate_part(value, Options, "options")


def registered_plane(cam: CellCamera, camera_name: str | None, store) -> dict[str, Any] | None:
    """The plane registered with a fixed camera (``{"normal", "d_mm"}``), else None."""
    if camera_name is None or cam.T_flange_cam is not None:
        return None
    record = store.camera(camera_name)
    return None if record is None else record.get("plane")


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


def snap_warnings(cam: Camera, opts: Options | None = None) -> list[str]:
    """One warning per rotation of the request (the inline camera's extrinsics, ``options.robot_pose``)
    that was off orthonormal enough to be snapped visibly (``cell.ROTATION_SILENT``)."""
    poses = [("camera's T_base_cam", getattr(cam, "T_base_cam", None)),
             ("camera's T_flange_cam", getattr(cam, "T_flange_cam", None)),
             ("options.robot_pose", None if opts is None else opts.robot_pose)]
    return [w for what, T in poses if T is not None and (w := T.snap_warning(what)) is not None]


def grasps_of(records: list[dict[str, Any]]) -> list[Grasp]:
    specs = [GraspSpec.model_validate(r) for r in records]
    return [Grasp(s.name, s.T_obj_grasp.matrix(), np.asarray(s.approach_axis, float)) for s in specs]


def add_cell_frames(result: EstimateResult, bank: TemplateBank, cam: CellCamera, opts: Options,
                    grasps: list[Grasp], camera_name: str | None = None) -> EstimateResult:
    """The result with ``T_base_obj`` on every pose (when the extrinsics are known) and the grasps of
    the reported pose (the refined one, else the coarse one; none when not found), at the top level
    and on each of ``result.instances`` for that instance's own pose."""
    T_base_cam = base_from_cam(
        None if cam.T_base_cam is None else cam.T_base_cam.matrix(),
        None if cam.T_flange_cam is None else cam.T_flange_cam.matrix(),
        None if opts.robot_pose is None else opts.robot_pose.matrix())
    result.camera_name = camera_name
    if T_base_cam is not None:
        for pose in [result.coarse, result.refined, *result.candidates,
                     *(p for i in result.instances for p in (i.coarse, i.refined))]:
            if pose is not None:
                pose.T_base_obj = FramePose.from_matrix(T_base_cam @ rigid(pose.R, pose.t_mm))

    def placed(reported: PoseJSON | None) -> list[PlacedGraspJSON]:
        if reported is None or not grasps:
            return []
        return [PlacedGraspJSON(
            name=p.name, T_cam_grasp=FramePose.from_matrix(p.T_cam_grasp),
            T_base_grasp=None if p.T_base_grasp is None else FramePose.from_matrix(p.T_base_grasp),
            approach_angle_deg=p.approach_angle_deg, spin_deg=p.spin_deg)
            for p in place_grasps(rigid(reported.R, reported.t_mm), grasps, T_base_cam,
                                  symmetry_axis_obj=bank.symmetry_axis_obj,
                                  symmetry_point_obj=bank.symmetry_point_obj)]

    if result.found:
        result.grasps = placed(result.refined or result.coarse)
    for inst in result.instances:  # each its own answer: a cell picks the instance it can reach
        inst.grasps = placed(inst.refined or inst.coarse)
    return result


def estimate_result(record: dict[str, Any], bank: TemplateBank, data: bytes, cam: Camera, opts: Options, *,
                    max_pixels: int, camera_name: str | None = None, grasps: list[Grasp] | None = None,
                    default_deadline_ms: float | None = None,
                    appearance: Appearance | None = None) -> EstimateResult:
    """Image bytes -> EstimateResult (blocking: the API calls it from a worker thread; the CLI calls it
    too).

    The intrinsics and distances are held to the plausibility bounds (``service.bounds``) for the
    decoded image's size before the search, and so is the part's apparent size at the nearest distance
    searched (``bounds.check_apparent_size``). With a ``CellCamera`` (image size, extrinsics) the image
    size is checked too and the result gains the robot-frame poses and the placed ``grasps``.
    ``default_deadline_ms`` (the service's setting; None or 0: none) applies when ``opts`` give none.
    ``appearance``: the model's colours taught from its reference photos (``references.appearance_of``),
    which every candidate is then judged on too. On a plane, a part calibrated for one
    (``service/plane_calibrations``) is also judged on its visible edges' agreement; one not calibrated
    yet is answered with a warning saying so."""
    cell = isinstance(cam, CellCamera)
    if cell:
        size = image_size(data)
        if size is not None:  # from the header: refused before a pixel is decoded
            check_image_size(cam, size, camera_name)

    started_at = time.perf_counter()  # a deadline counts from here, decoding included
    image = decode_image(data, max_pixels=max_pixels)
    size = (image.shape[1], image.shape[0])
    if cell:
        check_image_size(cam, size, camera_name)
    check_plausible(cam, opts, size)
    check_apparent_size(bank, cam, opts, size, units=record.get("units") or "mm")
    kwargs = opts.estimate_kwargs()
    if kwargs["deadline_ms"] is None:
        kwargs["deadline_ms"] = default_deadline_ms or None
    kwargs["appearance"] = appearance
    kwargs["agreement"] = plane_agreement_of(record)  # read on a plane only
    out = estimate_image(bank, image, cam.to_intrinsics(), started_at=started_at, **kwargs)
    result = EstimateResult.from_output(record["id"], out)
    uncalibrated = plane_calibration_warning(record) if kwargs.get("plane") is not None else None
    result.warnings = (ModelInfo.from_record(record).warnings + snap_warnings(cam, opts) + result.warnings
                       + ([uncalibrated] if uncalibrated else []))
    if cell:
        result = add_cell_frames(result, bank, cam, opts, grasps or [], camera_name)
    return result
