"""The template bank: everything an estimate needs about a model, as stacked arrays.

Built once per model (``templates.build_bank``), stored as one record, loaded in milliseconds.
Templates are camera-independent: template ``n`` is the model seen with rotation ``R_tpl_obj[n]``
with its reference point ``centre_obj`` on the optical axis at ``reference_distance_mm``; its
borderline points carry normalised image coordinates, an edge orientation and the 3D model point
they came from, so an estimate can re-project them exactly for any intrinsics and distance.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field

import numpy as np

BANK_FORMAT_VERSION = 1


@dataclass(frozen=True)
class TemplateBank:
    # --- views (N of them) ---
    R_tpl_obj: np.ndarray  # (N, 3, 3) float64: object orientation in the template camera frame
    view_params_deg: np.ndarray  # (N, 2) float64: (tilt, 0) for a symmetric part; (azimuth, elevation) else
    offsets: np.ndarray  # (N + 1,) int64: template n's points are [offsets[n], offsets[n + 1])
    # --- borderline points (P of them, all templates stacked) ---
    xy_n: np.ndarray  # (P, 2) float32: normalised image coords (x/z, y/z) at the reference distance
    theta_rad: np.ndarray  # (P,) float32: edge orientation in the image, [0, pi), undirected
    p_obj: np.ndarray  # (P, 3) float32: mm, object frame; the model point the border point came from
    # --- the model ---
    centre_obj: np.ndarray  # (3,) float64: mm, object frame; the point put on the optical axis
    reference_distance_mm: float
    vertices_mm: np.ndarray  # (V, 3) float32: mm, object frame (for overlays and re-extraction)
    faces: np.ndarray  # (F, 3) int32
    extents_mm: np.ndarray  # (3,) float64
    diameter_mm: float
    symmetry_axis_obj: np.ndarray | None  # (3,) unit, object frame; None = no continuous symmetry
    symmetry_point_obj: np.ndarray | None  # (3,) mm, object frame: a point on that axis (None with it)
    grid: dict = field(default_factory=dict)  # the grid options the bank was built with (steps, ranges)

    @property
    def n_templates(self) -> int:
        return int(len(self.R_tpl_obj))

    def points(self, n: int) -> slice:
        return slice(int(self.offsets[n]), int(self.offsets[n + 1]))

    def to_arrays(self) -> dict[str, np.ndarray]:
        """Flat dict of arrays (for ``np.savez``); ``from_arrays`` inverts it exactly."""
        d = asdict(self)
        special = ("grid", "symmetry_axis_obj", "symmetry_point_obj", "reference_distance_mm", "diameter_mm")
        out = {k: np.asarray(v) for k, v in d.items() if k not in special}
        out["reference_distance_mm"] = np.float64(self.reference_distance_mm)
        out["diameter_mm"] = np.float64(self.diameter_mm)
        for k in ("symmetry_axis_obj", "symmetry_point_obj"):
            v = getattr(self, k)
            out[k] = np.zeros(0) if v is None else np.asarray(v, float)
        import json

        out["grid_json"] = np.frombuffer(json.dumps(self.grid, sort_keys=True).encode(), np.uint8)
        out["format_version"] = np.int64(BANK_FORMAT_VERSION)
        return out

    @classmethod
    def from_arrays(cls, a) -> TemplateBank:
        import json

        axis = np.asarray(a["symmetry_axis_obj"], float)
        point = np.asarray(a["symmetry_point_obj"], float)
        return cls(
            R_tpl_obj=np.asarray(a["R_tpl_obj"]), view_params_deg=np.asarray(a["view_params_deg"]),
            offsets=np.asarray(a["offsets"]), xy_n=np.asarray(a["xy_n"]),
            theta_rad=np.asarray(a["theta_rad"]), p_obj=np.asarray(a["p_obj"]),
            centre_obj=np.asarray(a["centre_obj"]), reference_distance_mm=float(a["reference_distance_mm"]),
            vertices_mm=np.asarray(a["vertices_mm"]), faces=np.asarray(a["faces"]),
            extents_mm=np.asarray(a["extents_mm"]), diameter_mm=float(a["diameter_mm"]),
            symmetry_axis_obj=None if axis.size == 0 else axis,
            symmetry_point_obj=None if point.size == 0 else point,
            grid=json.loads(bytes(np.asarray(a["grid_json"], np.uint8)).decode()),
        )
