"""Wire models of a part's reference photos (``service.references``, ``POST /models/{id}/references``)."""

from __future__ import annotations

from pydantic import BaseModel, Field

from service.schemas import CellCamera, Transform


class ReferencePhoto(BaseModel):
    """One stored reference photo (without its image bytes)."""

    index: int = Field(description="0-based, in the order the photos were posted")
    camera: CellCamera = Field(description="the camera as the post gave it, resolved (a registered camera's "
                               "intrinsics as they were then)")
    camera_name: str | None = Field(description="the registered camera the post named, else null")
    T_cam_obj: Transform = Field(description="the part's pose in the photo (R snapped to a rotation)")
    width: int = Field(description="image width, pixels")
    height: int = Field(description="image height, pixels")


class ReferenceAdded(BaseModel):
    """``POST /models/{id}/references``: the photo is stored and taught."""

    model_id: str
    index: int = Field(description="the new photo's index")
    references: int = Field(description="reference photos the model has now")
    max_references: int = Field(description="the most it keeps (DELETE them to start again)")
    known_fraction: float = Field(description="0..1, share of the mesh's faces whose colour all the photos "
                                  "teach")
    faces_taught_by_this_view: int = Field(description="faces this photo alone shows well enough to teach")
    plain: bool = Field(description="the photos show a plain part (the untextured shading model explains "
                        "them, in shades of one colour): its taught colours are kept but not used, and "
                        "estimates are judged as for an untaught part")
    reference_shading_r2: float = Field(description="0..1, median over the photos of the untextured shading "
                                        "model's fit at their poses (plain at >= 0.8 with hue_share < 0.01)")
    hue_share: float = Field(description="0..1, share of the taught colours' variance off their main colour "
                             "axis")
    agreement: float | None = Field(description="-1..1, median over the photos of each one's appearance as "
                                    "the others teach it (null with one photo): do they agree on colours?")
    used: bool = Field(description="whether estimates are judged on the taught colours: not plain, and the "
                       "photos agree (agreement >= 0.6, or >= 0.5 once calibrated; so at least two "
                       "photos)")
    calibrated: bool = Field(False, description="the part's operating point is calibrated on these photos: "
                             "each was searched as a frame, taught by the others, and every pose found there "
                             "away from the photo's own (MSPD >= 20 px at 640 px wide) counted as a wrong "
                             "answer this cell can produce; a calibrated part is also searched more widely")
    calibration_wrong_score: float | None = Field(
        None, description="0..1, the highest verification score of such a wrong pose (null: none judged, or "
                          "not calibrated)")
    min_score: float | None = Field(
        None, description="0..1, the operating point this part's estimates use when options.min_score is not "
                          "given: above calibration_wrong_score, never under the global default (null: the "
                          "global default, the colours not used)")
    calibration_status: str | None = Field(
        None, description="the calibration of the current photos: 'queued', 'running' (see "
                          "calibration_progress), 'calibrated', 'not_requested' (posted with "
                          "calibrate=false), 'not_calibratable' (one photo, or photos plain or disagreeing); "
                          "it runs in the "
                          "background after the POST answers: poll GET /models/{id}/references")
    calibration_progress: float | None = Field(
        None, description="0..1, the share of the stored photos searched by the running calibration (1 when "
                          "calibrated; null when none is due)")
    warnings: list[str] = Field(
        default_factory=list, description="what the post was accepted with but should fix: a pose's (or the "
        "inline camera's extrinsics') R off orthonormal by up to 0.01 (max |R R^T - I|), snapped to the "
        "nearest rotation; empty when nothing")


class References(BaseModel):
    """``GET /models/{id}/references``."""

    model_id: str
    references: int = Field(description="reference photos stored (0: the part is untaught)")
    max_references: int
    known_fraction: float | None = Field(
        description="0..1, share of the mesh's faces whose colour the photos teach; null while the model "
                    "is not ready")
    plain: bool | None = Field(None, description="as in the POST's answer; null without photos or while the "
                               "model is not ready")
    reference_shading_r2: float | None = None
    hue_share: float | None = None
    agreement: float | None = None
    used: bool | None = None
    calibrated: bool | None = None
    calibration_wrong_score: float | None = None
    min_score: float | None = None
    calibration_status: str | None = Field(None, description="as in the POST's answer; null without photos")
    calibration_progress: float | None = None
    views: list[ReferencePhoto]
