"""Wire models: the API contract as pydantic models, and the one place they meet ``service.vision``.

Requests are converted to vision dataclasses once (``Camera.to_intrinsics``); results are built
from pipeline dataclasses once (``EstimateResult.from_output``). Nothing below ``service.api``
sees these classes (``reference_schemas`` holds the reference photos' models, ``form_parts`` the
parsing of a form part's JSON into them). Lengths are millimetres, angles degrees, poses
``T_cam_obj`` (see API.md).
"""

from __future__ import annotations

import base64
from datetime import datetime
from typing import Annotated, Any, Literal

import numpy as np
from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    PrivateAttr,
    field_validator,
    model_validator,
)

from service.cell import extent_warnings, nearest_rotation, rigid, snap_warning, watertight_warnings
from service.plane_calibrations import plane_calibration_info
from service.vision.estimate.plane import PLANE_TOLERANCE_MM
from service.vision.estimate.verdict import AGREEMENT_EVIDENCE
from service.vision.geometry.camera import Intrinsics
from service.vision.geometry.frames import Pose, euler_xyz_deg_from_R, quat_xyzw_from_R
from service.vision.pipeline import EstimateOutput, PoseCandidate, RefinedPose

Units = Literal["mm", "cm", "m", "in"]
SymmetryOption = Literal["auto", "none", "x", "y", "z"]
Status = Literal["queued", "building", "ready", "failed"]
Vec3 = Annotated[list[float], Field(min_length=3, max_length=3)]


class _Request(BaseModel):
    """Request JSON: unknown keys and NaN/inf are errors (a typo must not be silently ignored)."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)


# --- requests ---------------------------------------------------------------------------------------

class Camera(_Request):
    """Pinhole intrinsics in pixels, OpenCV convention; ``dist`` = [k1, k2, p1, p2[, k3[, k4, k5, k6]]]."""

    fx: float = Field(gt=0, description="focal length in pixels along u (columns)")
    fy: float = Field(gt=0, description="focal length in pixels along v (rows)")
    cx: float = Field(description="principal point u, pixels (centre of the top-left pixel is 0)")
    cy: float = Field(description="principal point v, pixels")
    dist: list[float] | None = Field(None, description="OpenCV distortion coefficients: 4, 5 or 8 numbers")

    @field_validator("dist")
    @classmethod
    def _dist_length(cls, v: list[float] | None) -> list[float] | None:
        if v is not None and len(v) not in (4, 5, 8):
            raise ValueError(f"dist must have 4, 5 or 8 coefficients, not {len(v)}")
        return v

    def to_intrinsics(self) -> Intrinsics:
        dist = tuple(self.dist) if self.dist is not None and any(self.dist) else None
        return Intrinsics(self.fx, self.fy, self.cx, self.cy, dist)


class RectROI(_Request):
    """A rectangle of the image, pixels: top-left (x, y) = (u, v), w columns wide, h rows high."""

    x: float = Field(description="u (column) of the left edge, pixels")
    y: float = Field(description="v (row) of the top edge, pixels")
    w: float = Field(description="width, pixels, > 0")
    h: float = Field(description="height, pixels, > 0")

    @model_validator(mode="after")
    def _area(self) -> RectROI:
        if not (self.w > 0 and self.h > 0):
            raise ValueError(f"roi has zero area (w {self.w:g}, h {self.h:g}): give w and h greater than 0")
        return self


Polygon = Annotated[list[Annotated[list[float], Field(min_length=2, max_length=2)]], Field(max_length=1000)]
MAX_INSTANCES = 50
MAX_DEADLINE_MS = 600_000.0


class Options(_Request):
    distance_mm: float | None = Field(
        None, gt=0, description="known distance from the camera to the object origin along z, mm")
    distance_range_mm: tuple[float, float] | None = Field(
        None, description="[min, max] distance to search, mm, 0 < min < max (default: the pipeline's)")
    refine: bool = Field(True, description="run the Levenberg-Marquardt refinement")
    top_k: int = Field(5, ge=1, le=50, description="number of coarse candidates to return")
    overlay: bool = Field(False, description="add overlay_png_base64 (coarse contour dashed, refined solid; "
                          "when nothing is found, the best rejected candidate dotted)")
    min_score: float | None = Field(
        None, ge=0, le=1, description="operating point of the verdict: found needs verdict.score >= this "
        "(default: the service's, chosen for precision; lower finds more and trusts less)")
    robot_pose: Transform | None = Field(
        None, description="T_base_flange, the robot's flange pose when the image was taken: required for an "
        "eye-in-hand camera (T_flange_cam), ignored otherwise")
    roi: RectROI | Polygon | None = Field(
        None, description="region of interest, pixels: {x, y, w, h} or a polygon [[u, v], ...] of at least 3 "
        "points; only placements whose projected centre lies inside are searched")
    max_instances: int = Field(1, ge=1, le=MAX_INSTANCES, description="report up to this many distinct "
                               "found instances in instances (each verified on its own)")
    deadline_ms: float | None = Field(
        None, gt=0, le=MAX_DEADLINE_MS, description="time budget of this estimate, ms, counted from when the "
        "service starts decoding the image (default: the service's POSE_DEADLINE_MS, unset: none): the "
        "search is anytime, it stops starting new work when the budget no longer leaves time to verify a "
        "candidate and answers with the best verified result so far (deadline_reached true, "
        "deadline_stopped_in and candidates_checked say how far it got; verdict.reason deadline when nothing "
        "was found). The best proposal is always checked, so an answer may come later than the budget")
    sort: Literal["score", "distance", "height"] = Field(
        "score", description="order of instances: score (verification score, highest first), distance "
        "(the part's centre nearest the camera first) or height (the part's centre highest above the "
        "plane first; needs plane)")
    plane: Plane | None = Field(
        None, description="the supporting plane the parts rest on, camera frame: points p with normal . p = "
        "d_mm, the normal pointing out of the surface towards the camera (d_mm < 0). The search then runs "
        "over the part's stable resting poses, spins about the normal and positions on the plane, and a "
        "found part must rest on it within plane_tolerance_mm")
    plane_tolerance_mm: float = Field(
        PLANE_TOLERANCE_MM, gt=0, le=1000, description="with plane: a found part's lowest point lies within "
        "this distance of the plane, mm")

    @field_validator("roi")
    @classmethod
    def _polygon(cls, v: RectROI | list[list[float]] | None) -> RectROI | list[list[float]] | None:
        from service.vision.estimate.roi import polygon_area, segments_cross

        if isinstance(v, list):
            if len(v) < 3:
                n = len(v)
                raise ValueError(f"roi polygon has {n} point{'s' if n != 1 else ''}: give at least 3 [u, v] "
                                 "points")
            if segments_cross(np.array(v)):
                raise ValueError("roi polygon crosses itself: list its points in order round its outline")
            if polygon_area(np.array(v)) <= 0:
                raise ValueError("roi polygon has zero area: give at least 3 points not on one line")
        return v

    def roi_uv(self) -> np.ndarray | None:
        """The region of interest as an (N, 2) float64 polygon, pixels (None: the whole image)."""
        from service.vision.estimate.roi import rect_polygon

        if self.roi is None:
            return None
        if isinstance(self.roi, RectROI):
            return rect_polygon(self.roi.x, self.roi.y, self.roi.w, self.roi.h)
        return np.asarray(self.roi, float)

    def estimate_kwargs(self) -> dict[str, Any]:
        """The options as ``pipeline.estimate``'s keyword arguments."""
        return {"distance_mm": self.distance_mm, "distance_range_mm": self.distance_range_mm,
                "refine": self.refine, "top_k": self.top_k, "overlay": self.overlay,
                "min_score": self.min_score, "roi_uv": self.roi_uv(), "max_instances": self.max_instances,
                "sort": self.sort, "plane": None if self.plane is None else self.plane.to_plane(),
                "plane_tolerance_mm": self.plane_tolerance_mm, "deadline_ms": self.deadline_ms}

    @model_validator(mode="after")
    def _distances(self) -> Options:
        if self.distance_range_mm is not None:
            lo, hi = self.distance_range_mm
            if not 0 < lo < hi:
                raise ValueError(f"distance_range_mm must satisfy 0 < min < max, got [{lo:g}, {hi:g}]")
            if self.distance_mm is not None:
                raise ValueError("give distance_mm or distance_range_mm, not both")
        if self.sort == "height" and self.plane is None:
            raise ValueError("sort 'height' orders the parts by their height above the supporting plane: "
                             "send options.plane with it, or sort by score or distance")
        if self.plane is not None and self.distance_mm is not None:
            raise ValueError("give plane or distance_mm, not both: the plane fixes every placement's "
                             "distance (distance_range_mm may limit the search on it)")
        return self


# --- results ----------------------------------------------------------------------------------------

class FramePose(BaseModel):
    """``T_<to>_<from>``: a point X (mm) of frame ``from`` lands at ``R @ X + t_mm`` in frame ``to``."""

    R: list[Vec3] = Field(description="3x3 rotation, row-major", min_length=3, max_length=3)
    t_mm: Vec3 = Field(description="translation, mm, camera frame")
    euler_xyz_deg: Vec3 = Field(description="(rx, ry, rz) degrees with R = Rx(rx) @ Ry(ry) @ Rz(rz)")
    quaternion_xyzw: Annotated[list[float], Field(min_length=4, max_length=4)] = Field(
        description="unit quaternion (x, y, z, w)")

    @staticmethod
    def fields_from(pose: Pose) -> dict[str, Any]:
        R = np.asarray(pose.R, float)
        return {"R": R.tolist(), "t_mm": np.asarray(pose.t_mm, float).tolist(),
                "euler_xyz_deg": euler_xyz_deg_from_R(R).tolist(),
                "quaternion_xyzw": quat_xyzw_from_R(R).tolist()}

    @classmethod
    def from_matrix(cls, T: np.ndarray) -> FramePose:
        """(4, 4) homogeneous transform, mm -> pose JSON."""
        T = np.asarray(T, float)
        return cls(**cls.fields_from(Pose(T[:3, :3], T[:3, 3])))


class PoseJSON(FramePose):
    """``T_cam_obj``: a model point X (mm, model frame) lands at ``R @ X + t_mm`` in the camera frame."""

    T_base_obj: FramePose | None = Field(
        None, description="the same pose in the robot's base frame, when the camera's extrinsics are known "
        "(T_base_cam, or T_flange_cam with options.robot_pose); else null")


class Candidate(PoseJSON):
    cost: float = Field(description="mean directional chamfer distance, px (lower is better)")
    score: float = Field(description="0..1, share of border points near a matching image edge (higher wins)")

    @classmethod
    def from_candidate(cls, c: PoseCandidate) -> Candidate:
        return cls(**cls.fields_from(c.pose), cost=float(c.cost), score=float(c.score))


class Coarse(Candidate):
    """The best template placement (before refinement)."""


class Refined(Candidate):
    iterations: int = Field(description="Levenberg-Marquardt iterations")
    inlier_ratio: float = Field(description="0..1, share of border points inside the robust-loss threshold")

    @classmethod
    def from_refined(cls, r: RefinedPose) -> Refined:
        return cls(**cls.fields_from(r.pose), cost=float(r.cost), score=float(r.score),
                   iterations=int(r.iterations), inlier_ratio=float(r.inlier_ratio))


class Timing(BaseModel):
    edges: float
    coarse: float
    refine: float
    total: float


class VerdictJSON(BaseModel):
    found: bool
    score: float = Field(description="0..1 verification score of the pose reported, or of the best rejected "
                         "candidate when nothing is found")
    reason: str = Field(description="found | no_candidate | outside_distance_range | outside_image | "
                        "off_plane | low_support | interior_edges | region_mismatch | shading_mismatch | "
                        "appearance_mismatch | generic_outline | low_score | edges_disagree | "
                        "rival_at_place | deadline (the search stopped at options.deadline_ms before finding "
                        "one)")
    evidence: dict[str, float] = Field(description="the evidence the score was computed from: edge_support, "
                                       "unexplained, colour_edge, polarity, region, region_low, in_image, "
                                       "generic (fractions; see docs/API.md), distinct_px (pixels); with "
                                       "options.plane also edge_agreement, inner_agreement, "
                                       "outline_agreement, edge_coverage, outline_coverage (fractions), "
                                       "plane_gap_mm, the height of the part's lowest point above the "
                                       "plane, mm; for a found part with a mirror plane also twin_score, "
                                       "the score of its mirror twin (the same outline, near and far "
                                       "faces swapped); for a part with reference photos also "
                                       "appearance (-1..1, the taught colours' correlation with the "
                                       "image's) and appearance_known (the share of the inside whose "
                                       "colour was taught)")


class InstanceJSON(BaseModel):
    """One found instance, refined and verified on its own."""

    coarse: Coarse
    refined: Refined | None = Field(description="null when refine is false")
    verdict: VerdictJSON
    grasps: list[PlacedGraspJSON] = Field(
        default_factory=list, description="the model's grasps where this instance lies (its refined pose, "
        "else its coarse one), most reachable first, like the top-level grasps of instances[0]; empty when "
        "none are registered")


def _verdict_json(v) -> VerdictJSON:
    return VerdictJSON(found=v.found, score=float(v.score), reason=v.reason,
                       evidence={k: float(x) for k, x in v.evidence.items()})


class EstimateResult(BaseModel):
    model_id: str
    image_size: Annotated[list[int], Field(min_length=2, max_length=2)] = Field(description="[w, h], pixels")
    found: bool = Field(description="false when no placement is supported by the image (object absent)")
    coarse: Coarse | None
    refined: Refined | None = Field(description="null when refine is false or nothing was found")
    candidates: list[Candidate] = Field(description="the top_k coarse placements, best first")
    timing_ms: Timing = Field(description="milliseconds per stage")
    overlay_png_base64: str | None = Field(None, description="PNG of the image with the contours (overlay)")
    camera_name: str | None = Field(None, description="the registered camera the request named, else null")
    grasps: list[PlacedGraspJSON] = Field(
        default_factory=list, description="the model's grasps where the part was found (empty when not found "
        "or none registered), most reachable first: by approach_angle_deg")
    warnings: list[str] = Field(default_factory=list, description="the model's upload warnings (ModelInfo), "
                                "and a rotation of the request (options.robot_pose, the inline camera's "
                                "extrinsics) off orthonormal by up to 0.01, snapped to the nearest rotation")
    verdict: VerdictJSON | None = Field(None, description="why found is true or false, with its evidence")
    instances: list[InstanceJSON] = Field(
        default_factory=list, description="the found instances (at most options.max_instances), distinct, "
        "sorted by options.sort; the top-level coarse, refined and verdict describe instances[0]; empty when "
        "nothing is found")
    deadline_reached: bool = Field(
        False, description="the search stopped early at the deadline (options.deadline_ms or the service's): "
        "the answer is the best verified result found by then")
    deadline_stopped_in: Literal["edges", "search", "checks", "second pass"] | None = Field(
        None, description="the stage the deadline stopped: search (the coarse search was cut short), checks "
        "(fewer candidates were refined and verified than the search proposed), second pass (the fallback "
        "proposals after the first ones failed); null when it did not")
    candidates_checked: int = Field(
        0, ge=0, description="candidates refined and verified for this answer (at least 1 when the search "
        "proposed any, deadline or not)")

    @classmethod
    def from_output(cls, model_id: str, out: EstimateOutput) -> EstimateResult:
        overlay = None if out.overlay_png is None else base64.b64encode(out.overlay_png).decode("ascii")
        return cls(
            model_id=model_id, image_size=[int(v) for v in out.image_size], found=bool(out.found),
            coarse=None if out.coarse is None else Coarse.from_candidate(out.coarse),
            refined=None if out.refined is None else Refined.from_refined(out.refined),
            candidates=[Candidate.from_candidate(c) for c in out.candidates],
            timing_ms=Timing(**{k: float(out.timing_ms.get(k, 0.0)) for k in Timing.model_fields}),
            overlay_png_base64=overlay,
            verdict=_verdict_json(out.verdict),
            instances=[InstanceJSON(coarse=Coarse.from_candidate(i.coarse),
                                    refined=None if i.refined is None else Refined.from_refined(i.refined),
                                    verdict=_verdict_json(i.verdict)) for i in out.instances],
            deadline_reached=bool(out.deadline_reached),
            deadline_stopped_in=out.deadline_stopped_in,
            candidates_checked=int(out.candidates_checked),
            warnings=list(out.warnings),
        )


# --- models -----------------------------------------------------------------------------------------

class Symmetry(BaseModel):
    type: Literal["none", "continuous"]
    axis: Vec3 | None = Field(description="unit axis in the model frame (continuous symmetry), else null")


class PlaneCalibrationInfo(BaseModel):
    status: Literal["queued", "running", "calibrated", "failed", "not_requested"] = Field(
        description="the part's calibration for parts on a plane (rendered scenes of it among look-alike "
        "shapes, in the background once it is ready): queued, running (see progress), calibrated, failed "
        "(see error; not tried again), or not_requested (POSE_PLANE_CALIBRATION_SCENES=0)")
    progress: float = Field(description="0..1, the share of its scenes judged")
    agreement_min: float | None = Field(
        description="the agreement of the visible edges' gradients (min of the evidence agreement_along "
        "names and polarity) a pose on a plane must reach to be found on it; null until calibrated, or when "
        "no agreement kept the wrong poses of its scenes out (a plain shape among look-alikes)")
    wrong_max: float | None = Field(description="the highest agreement a wrong pose reached in its scenes")
    agreement_floor: float | None = Field(
        None, description="the least agreement a pose on a plane is found with, whatever its other evidence "
        "(verdict reason edges_disagree below it): 0.08 under the lowest a right pose read in its scenes; "
        "null until calibrated")
    agreement_along: Literal[AGREEMENT_EVIDENCE] | None = Field(
        None, description="the evidence agreement_min and agreement_floor read: edge_agreement (every "
        "visible edge), or outline_agreement (the outline alone), edge_coverage or outline_coverage "
        "(the same by the edges' extent) where that let a tenth more of its scenes' right poses reach "
        "their point; null until calibrated")
    agreement_min_by_rest: list[float | None] | None = Field(
        None, description="the agreement_min of a pose in each of the part's resting families (in the "
        "order of its stable poses), 0.08 above the highest a wrong pose in that family reached, where its "
        "scenes held at least 4 wrong poses in it a scene; null entries read agreement_min; null until "
        "calibrated")
    agreement_min_place: float | None = Field(
        None, description="the agreement a pose on a plane must reach to be found where no other candidate "
        "at its place (silhouette IoU >= 0.4) agrees more (verdict reason rival_at_place where one does): "
        "0.08 above the highest a wrong pose away from every copy reached in its scenes; null when "
        "uncalibrated, or when in its scenes a wrong pose was the best at a copy's place there")
    scenes: int | None = Field(description="rendered scenes it was calibrated on (null until calibrated)")
    error: str | None = Field(None, description="why it failed (status failed), else null")


class ModelInfo(BaseModel):
    id: str
    name: str
    status: Status
    progress: float = Field(description="0..1, template build progress")
    error: str | None = Field(description="why the build failed (status failed), else null")
    n_templates: int | None = Field(description="number of templates (null until ready)")
    units: Units = Field(description="the unit the mesh was uploaded in (converted to mm once)")
    extents_mm: Vec3 = Field(description="bounding-box size of the mesh, mm, model frame")
    symmetry: Symmetry | None = Field(description="continuous rotational symmetry; null until known")
    templates: dict[str, Any] = Field(description="template-grid options the model is built with")
    created_at: datetime
    warnings: list[str] = Field(
        default_factory=list, description="what looks wrong about the upload, e.g. a size that suggests the "
        "wrong units (largest side outside 1 mm .. 3 m); empty when nothing does")
    references: int = Field(0, description="reference photos the part's colours are taught from "
                            "(POST /models/{id}/references); 0: untaught")
    plane_calibration: PlaneCalibrationInfo | None = Field(
        None, description="how far the part's calibration for parts on a plane is (null until it is ready)")

    @classmethod
    def from_record(cls, record: dict[str, Any], plane_scenes: int | None = None) -> ModelInfo:
        """``plane_scenes``: the service's ``plane_calibration_scenes`` (None: not known to the caller)."""
        fields = {k: record.get(k) for k in cls.model_fields
                  if k not in ("warnings", "references", "plane_calibration")}
        return cls.model_validate({**fields, "references": int(record.get("references") or 0),
                                   "plane_calibration": plane_calibration_info(record, plane_scenes),
                                   "warnings": extent_warnings(record.get("extents_mm") or [],
                                                               record.get("units") or "mm")
                                   + watertight_warnings(record.get("watertight"),
                                                         record.get("open_edges") or 0,
                                                         record.get("nonmanifold_edges") or 0)})


class Health(BaseModel):
    status: Literal["ok"]
    version: str
    ready: bool = Field(
        True, description="false while the process compiles or loads its kernels at start-up (state "
        "starting): estimates are answered meanwhile, each paying for the kernels it needs; a probe that "
        "routes frames waits for true")
    state: Literal["starting", "ready"] = Field("ready", description="starting (the warm-up runs) or ready")
    store: Literal["disk", "redis"] = Field(
        description="the store this replica uses, and it answers (else 503): disk = the diskcache in "
        "POSE_CACHE_DIR, redis = POSE_STORE")


class Error(BaseModel):
    detail: str = Field(description="one sentence: what is wrong and how to fix it")


# --- the cell: cameras with extrinsics, robot poses, grasps (service.cell) ---------------------------

CAMERA_NAME_PATTERN = r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,63}$"


class Transform(_Request):
    """A rigid transform ``T_<to>_<from>`` as a client sends it: ``{"R": 3x3 row-major, "t_mm": [x, y, z]}``.

    R must be a rotation within ``service.cell.ROTATION_ATOL`` and is snapped to the nearest one;
    ``snap_warning`` says so when the R sent was off by more than ``ROTATION_SILENT``."""

    R: list[Vec3] = Field(description="3x3 rotation, row-major (off orthonormal by up to 0.01, max |R R^T - "
                          "I|: snapped to the nearest rotation)", min_length=3, max_length=3)
    t_mm: Vec3 = Field(description="translation, mm")
    _R_sent: list[list[float]] | None = PrivateAttr(None)  # R as sent, when the snap changed it

    @field_validator("R")
    @classmethod
    def _rotation(cls, v: list[list[float]]) -> list[list[float]]:
        nearest_rotation(v)  # ValueError beyond ROTATION_ATOL, or a reflection
        return v

    @model_validator(mode="after")
    def _snap(self) -> Transform:
        snapped = nearest_rotation(self.R).tolist()
        if snapped != self.R:
            self._R_sent, self.R = self.R, snapped
        return self

    def snap_warning(self, what: str) -> str | None:
        """A warning that ``what`` (e.g. "options.robot_pose") had its R snapped, else None."""
        return None if self._R_sent is None else snap_warning(what, self._R_sent, self.R)

    def matrix(self) -> np.ndarray:
        """(4, 4) float64 homogeneous transform, mm."""
        return rigid(self.R, self.t_mm)


class Plane(_Request):
    """A plane in the camera frame: the points p (mm) with ``normal . p = d_mm``; kept with a unit normal."""

    normal: Vec3 = Field(description="plane normal, camera frame (scaled to unit length, d_mm with it)")
    d_mm: float = Field(description="offset: normal . p = d_mm for p on the plane, mm")

    @model_validator(mode="after")
    def _unit(self) -> Plane:
        n = float(np.linalg.norm(self.normal))
        if not n > 1e-12:
            raise ValueError("plane.normal must not be the zero vector")
        self.normal = [float(x) / n for x in self.normal]
        self.d_mm = float(self.d_mm) / n
        if self.d_mm == 0:
            raise ValueError("plane passes through the camera (d_mm 0): a supporting plane lies in front of "
                             "the camera, with d_mm < 0 in mm")
        if self.d_mm > 0:
            raise ValueError(f"plane has d_mm {self.d_mm:g} > 0, so its normal points away from the camera: "
                             "the normal must point out of the surface towards the camera; flip the signs "
                             "of normal and d_mm")
        return self

    def to_plane(self):
        """The vision core's ``Plane`` (unit normal, camera frame)."""
        from service.vision.geometry.plane import Plane as VisionPlane

        return VisionPlane(np.asarray(self.normal, float), float(self.d_mm))


class CellCamera(Camera):
    """A camera as an estimate may send it inline: the intrinsics, optionally the image size it takes
    and its extrinsics (one of ``T_base_cam``, eye-to-hand, or ``T_flange_cam``, eye-in-hand)."""

    width: int | None = Field(None, gt=0, description="image width the intrinsics belong to, pixels")
    height: int | None = Field(None, gt=0, description="image height the intrinsics belong to, pixels")
    T_base_cam: Transform | None = Field(
        None, description="eye-to-hand: the camera's pose in the robot's base frame (hand-eye result)")
    T_flange_cam: Transform | None = Field(
        None, description="eye-in-hand: the camera's pose in the robot's flange frame (hand-eye result); "
        "each estimate then needs options.robot_pose")

    @model_validator(mode="after")
    def _one_mounting(self) -> CellCamera:
        if self.T_base_cam is not None and self.T_flange_cam is not None:
            raise ValueError("give T_base_cam (a camera fixed in the cell, eye-to-hand) or T_flange_cam (a "
                             "camera on the robot's flange, eye-in-hand), not both")
        if (self.width is None) != (self.height is None):
            raise ValueError("give width and height together (the image size the intrinsics belong to)")
        return self

    def mounting_kind(self) -> Literal["eye-to-hand", "eye-in-hand", "none"]:
        if self.T_base_cam is not None:
            return "eye-to-hand"
        return "eye-in-hand" if self.T_flange_cam is not None else "none"


class CameraSpec(CellCamera):
    """``PUT /cameras/{name}``: intrinsics, the image size, optional extrinsics and supporting plane."""

    width: int = Field(gt=0, description="image width the camera sends, pixels")
    height: int = Field(gt=0, description="image height the camera sends, pixels")
    plane: Plane | None = Field(None, description="default supporting plane, camera frame: an estimate with "
                                "this camera that sends neither options.plane nor options.distance_mm "
                                "searches on it (a fixed camera only; not for T_flange_cam)")


class CameraInfo(CameraSpec):
    """A registered camera as stored, with its name and how it is mounted."""

    name: str
    mounting: Literal["eye-to-hand", "eye-in-hand", "none"] = Field(
        description="eye-to-hand (T_base_cam), eye-in-hand (T_flange_cam) or none (no extrinsics)")
    warnings: list[str] = Field(
        default_factory=list, description="PUT only: what the request sent that was corrected (an extrinsics "
        "R off orthonormal, snapped to the nearest rotation); empty on GET")


class CameraRef(_Request):
    """An estimate's ``camera`` part naming a registered camera."""

    name: str = Field(description="the name of a camera registered with PUT /cameras/{name}")


class GraspSpec(_Request):
    """A gripper pose in the model frame."""

    name: str = Field(min_length=1, max_length=64, description="unique among the model's grasps")
    T_obj_grasp: Transform = Field(description="the grasp frame in the model frame (mm)")
    approach_axis: Vec3 = Field(
        [0.0, 0.0, 1.0], description="the direction the gripper moves in to close on the part, in the grasp "
        "frame (default +z, the tool axis)")

    @field_validator("approach_axis")
    @classmethod
    def _unit_axis(cls, v: list[float]) -> list[float]:
        n = float(np.linalg.norm(v))
        if not n > 1e-12:
            raise ValueError("approach_axis must not be the zero vector")
        return [float(x) / n for x in v]


class PlacedGraspJSON(BaseModel):
    """A grasp where the part was found."""

    name: str
    T_cam_grasp: FramePose = Field(description="the grasp in the camera frame")
    T_base_grasp: FramePose | None = Field(description="the grasp in the robot's base frame (null without "
                                           "extrinsics)")
    approach_angle_deg: float = Field(
        description="angle between the approach direction and straight down in the base frame (base -z), or, "
        "without extrinsics, the camera's viewing direction (+z): the sort key, smallest first")
    spin_deg: float = Field(description="rotation about a revolved part's symmetry axis applied to the grasp "
                            "to make it the most reachable of its equivalent ones; 0 for other parts")


Options.model_rebuild()
EstimateResult.model_rebuild()
