"""The template bank: everything an estimate needs about a model, as stacked arrays.

Built once per model (``model/templates.build_bank``), stored as one record, loaded in milliseconds.
Templates are camera-independent: template ``n`` is the model seen with rotation ``R_tpl_obj[n]``
with its reference point ``centre_obj`` on the optical axis at ``reference_distance_mm``; its
borderline points carry normalised image coordinates, an edge orientation and the 3D model point
they came from, so an estimate can re-project them exactly for any intrinsics and distance.

Beside the record: the bank's views as directions on the view sphere (neighbours, views within an
angle) and its border points sampled evenly along each template, each made once per bank. The build
room writes a bank and the estimate room reads it, so it sits between them, importing neither.
"""

from __future__ import annotations

import functools
import math
from dataclasses import asdict, dataclass, field

import numpy as np

from service.vision.memo import Memo

# 2: the stable resting poses (R_rest_obj, rest_probability); a version-1 bank loads with them
# None (the estimate then computes them from the mesh, once per bank).
# 3: the mirror planes (mirror_normals_obj, mirror_point_obj); an older bank loads with them None (the
# estimate computes them from the mesh, once per bank).
BANK_FORMAT_VERSION = 3


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
    # --- resting on a plane (model/stable.py): one pose per family, most probable first ---
    R_rest_obj: np.ndarray | None = None  # (S, 3, 3) float64: object -> resting frame (+z up)
    rest_probability: np.ndarray | None = None  # (S,) float64; None (both): a version-1 bank
    # --- mirror planes (model/mirror.py): each gives every pose an outline twin ---
    mirror_normals_obj: np.ndarray | None = None  # (M, 3) unit; M = 0: none; None (both): before version 3
    mirror_point_obj: np.ndarray | None = None  # (3,) mm: a point of every plane

    @property
    def n_templates(self) -> int:
        return int(len(self.R_tpl_obj))

    def points(self, n: int) -> slice:
        return slice(int(self.offsets[n]), int(self.offsets[n + 1]))

    def to_arrays(self) -> dict[str, np.ndarray]:
        """Flat dict of arrays (for ``np.savez``); ``from_arrays`` inverts it exactly."""
        d = asdict(self)
        special = ("grid", "symmetry_axis_obj", "symmetry_point_obj", "reference_distance_mm", "diameter_mm",
                   "R_rest_obj", "rest_probability", "mirror_normals_obj", "mirror_point_obj")
        out = {k: np.asarray(v) for k, v in d.items() if k not in special}
        out["reference_distance_mm"] = np.float64(self.reference_distance_mm)
        out["diameter_mm"] = np.float64(self.diameter_mm)
        for k in ("symmetry_axis_obj", "symmetry_point_obj"):
            v = getattr(self, k)
            out[k] = np.zeros(0) if v is None else np.asarray(v, float)
        if self.R_rest_obj is not None:
            out["R_rest_obj"] = np.asarray(self.R_rest_obj, float).reshape(-1, 3, 3)
            out["rest_probability"] = np.asarray(self.rest_probability, float)
        if self.mirror_normals_obj is not None:
            out["mirror_normals_obj"] = np.asarray(self.mirror_normals_obj, float).reshape(-1, 3)
            out["mirror_point_obj"] = np.asarray(self.mirror_point_obj, float)
        import json

        out["grid_json"] = np.frombuffer(json.dumps(self.grid, sort_keys=True).encode(), np.uint8)
        out["format_version"] = np.int64(BANK_FORMAT_VERSION)
        return out

    @classmethod
    def from_arrays(cls, a) -> TemplateBank:
        """The bank stored by ``to_arrays``, with its mesh's topology made (``silhouette.mesh_topology``,
        kept per mesh): every refinement's border trace reads it, and the first frame should not make it."""
        import json

        from service.vision.geometry.silhouette import mesh_topology

        axis = np.asarray(a["symmetry_axis_obj"], float)
        point = np.asarray(a["symmetry_point_obj"], float)
        bank = cls(
            R_tpl_obj=np.asarray(a["R_tpl_obj"]), view_params_deg=np.asarray(a["view_params_deg"]),
            offsets=np.asarray(a["offsets"]), xy_n=np.asarray(a["xy_n"]),
            theta_rad=np.asarray(a["theta_rad"]), p_obj=np.asarray(a["p_obj"]),
            centre_obj=np.asarray(a["centre_obj"]), reference_distance_mm=float(a["reference_distance_mm"]),
            vertices_mm=np.asarray(a["vertices_mm"]), faces=np.asarray(a["faces"]),
            extents_mm=np.asarray(a["extents_mm"]), diameter_mm=float(a["diameter_mm"]),
            symmetry_axis_obj=None if axis.size == 0 else axis,
            symmetry_point_obj=None if point.size == 0 else point,
            grid=json.loads(bytes(np.asarray(a["grid_json"], np.uint8)).decode()),
            R_rest_obj=np.asarray(a["R_rest_obj"], float) if "R_rest_obj" in a else None,
            rest_probability=np.asarray(a["rest_probability"], float) if "R_rest_obj" in a else None,
            mirror_normals_obj=(np.asarray(a["mirror_normals_obj"], float).reshape(-1, 3)
                                if "mirror_normals_obj" in a else None),
            mirror_point_obj=np.asarray(a["mirror_point_obj"], float) if "mirror_normals_obj" in a else None,
        )
        mesh_topology(bank.vertices_mm, bank.faces)
        return bank


# --- the bank's views on the view sphere (the coarse search moves between them) -------------------


def view_dirs_obj(bank: TemplateBank) -> np.ndarray:
    """(N, 3) each view's viewing direction (camera +z) in the object frame: R_tpl_obj.T @ e_z."""
    return bank.R_tpl_obj[:, 2, :]


_NEIGHBOURS = Memo(8)


def view_neighbours(bank: TemplateBank, k: int = 6) -> np.ndarray:
    """(N, k) the k nearest other views by viewing direction (object frame), once per bank."""

    def make():
        z = view_dirs_obj(bank)
        sim = z @ z.T
        np.fill_diagonal(sim, -np.inf)
        return np.argsort(-sim, axis=1)[:, :min(k, len(z) - 1)]

    return _NEIGHBOURS.get(bank, k, make)


def view_step_deg(bank: TemplateBank) -> float:
    """Angle between neighbouring views of the bank's grid."""
    key = "tilt_step_deg" if bank.symmetry_axis_obj is not None else "view_step_deg"
    return float(bank.grid[key])


def views_within(bank: TemplateBank, view: int, angle_deg: float) -> np.ndarray:
    """Bank views whose viewing direction (object frame) is within ``angle_deg`` of ``view``'s.

    For a revolved part also those near its mirror view (the axis tilted the other way, towards or
    away from the camera): the two silhouettes are equal in orthographic projection and differ only
    by perspective, so level A cannot tell them apart.
    """
    z = view_dirs_obj(bank)
    near = z @ z[view] >= math.cos(math.radians(angle_deg)) - 1e-9
    if bank.symmetry_axis_obj is not None:
        a = np.asarray(bank.symmetry_axis_obj, float)
        mirror = z[view] - 2 * (z[view] @ a) * a  # the viewing direction reflected in the axis' normal plane
        near |= z @ mirror >= math.cos(math.radians(angle_deg)) - 1e-9
    return np.flatnonzero(near)


# --- the bank's border points, sampled evenly along each template's border ---------------------------


@functools.lru_cache(maxsize=16)
def spread_order(count: int) -> np.ndarray:
    """A permutation of range(count) (indices along a closed border) whose every prefix is spread
    evenly round it (greedy farthest point): the scans' early termination then judges a template on
    points from all round its border, not on one stretch of it."""
    pos = np.arange(count)
    gap = np.full(count, count, np.int64)  # cyclic distance to the nearest chosen point
    order = np.empty(count, np.int64)
    for k in range(count):
        i = int(np.argmax(gap))
        order[k] = i
        d = np.abs(pos - i)
        gap = np.minimum(gap, np.minimum(d, count - d))
    order.flags.writeable = False
    return order


def subsample_border(bank: TemplateBank, n: int, count: int) -> np.ndarray:
    """Indices of ``count`` points spread evenly along template n's border."""
    s = bank.points(n)
    m = s.stop - s.start
    if m <= count:
        return np.arange(s.start, s.stop)
    return s.start + np.linspace(0, m, count, endpoint=False).astype(np.int64)


_TRIPLETS = Memo(8)


def border_triplets(bank: TemplateBank, count: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(N, count) indices of ``count`` points spread along every view's border, and of each point's
    predecessor and successor on that border (for the projected orientation). Made once per bank."""

    def make():
        idx = np.stack([np.resize(subsample_border(bank, n, count), count) for n in range(bank.n_templates)])
        lo = bank.offsets[:-1, None]
        hi = bank.offsets[1:, None]
        return idx, np.where(idx - 1 >= lo, idx - 1, hi - 1), np.where(idx + 1 < hi, idx + 1, lo)

    return _TRIPLETS.get(bank, count, make)
