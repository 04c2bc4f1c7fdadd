"""What the estimate reads of the part beyond its templates: mirror planes, resting poses (and which one a
pose on a plane is in), face areas, crease edges, the edges it shows at a pose.

Each is the bank's, or, for a bank built before banks held it, made from its mesh once per bank.
"""

from __future__ import annotations

import numpy as np
import trimesh

from service.vision.bank import TemplateBank
from service.vision.geometry.camera import Intrinsics
from service.vision.geometry.frames import Pose
from service.vision.memo import Memo
from service.vision.model.edge_points import VisibleEdges, crease_edges, visible_edges
from service.vision.model.mirror import MirrorPlanes, mirror_planes

_MADE = Memo(8)


def _mesh(bank: TemplateBank) -> trimesh.Trimesh:
    return trimesh.Trimesh(np.asarray(bank.vertices_mm, float), np.asarray(bank.faces), process=False)


def mirror_planes_of(bank: TemplateBank) -> MirrorPlanes:
    """The part's mirror planes (``model/mirror.py``); made for a bank of format version < 3."""
    if bank.mirror_normals_obj is not None:
        return MirrorPlanes(np.asarray(bank.mirror_normals_obj, float).reshape(-1, 3),
                            np.asarray(bank.mirror_point_obj, float))
    return _MADE.get(bank, "mirror", lambda: mirror_planes(_mesh(bank), axis_obj=bank.symmetry_axis_obj))


def resting_rotations(bank: TemplateBank) -> np.ndarray:
    """(S, 3, 3) ``R_rest_obj`` of the part's stable resting pose families; made for a bank of format
    version 1."""
    if bank.R_rest_obj is not None:
        return np.asarray(bank.R_rest_obj, float).reshape(-1, 3, 3)

    def make() -> np.ndarray:
        from service.vision.model.stable import stable_poses

        return stable_poses(_mesh(bank), axis_obj=bank.symmetry_axis_obj,
                            diameter_mm=bank.diameter_mm).R_rest_obj

    return _MADE.get(bank, "rest", make)


def rest_family(bank: TemplateBank, R_cam_obj: np.ndarray, normal_cam: np.ndarray) -> int:
    """The index of the resting family (``resting_rotations``) whose table normal, in the object frame,
    lies nearest the plane's (``normal_cam``) at rotation ``R_cam_obj``; -1 for a part without any. For a
    part with a symmetry axis, nearest by the normal's angle to the axis: a turn about it is the same pose."""
    rest = resting_rotations(bank)
    if not len(rest):
        return -1
    up_obj = np.asarray(R_cam_obj, float).T @ np.asarray(normal_cam, float)
    rest_up_obj = rest[:, 2, :]  # each family's table normal in the object frame
    if bank.symmetry_axis_obj is None:
        return int(np.argmax(rest_up_obj @ up_obj))
    axis = np.asarray(bank.symmetry_axis_obj, float)
    angle = np.arccos(np.clip(rest_up_obj @ axis, -1.0, 1.0)) - np.arccos(np.clip(up_obj @ axis, -1.0, 1.0))
    return int(np.argmin(np.abs(angle)))


def face_areas_mm2(bank: TemplateBank) -> np.ndarray:
    """(F,) float64 area of each face, mm^2."""
    def make() -> np.ndarray:
        v = np.asarray(bank.vertices_mm, float)[np.asarray(bank.faces)]
        return 0.5 * np.linalg.norm(np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0]), axis=1)

    return _MADE.get(bank, "face_area", make)


_EDGES = Memo(32)


def crease_edges_of(bank: TemplateBank) -> np.ndarray:
    """(E, 2, 3) the part's crease edges (``model/edge_points.crease_edges``), made once per bank."""
    return _EDGES.get(bank, "creases", lambda: crease_edges(bank.vertices_mm, bank.faces))


_SHOWN = Memo(2)  # a verdict and the polish after it: the latest poses only


def shown_edges(bank: TemplateBank, pose: Pose, intr: Intrinsics, size: tuple[int, int]
                ) -> VisibleEdges | None:
    """The edges the part shows at ``pose`` in an image of ``size`` (``model/edge_points.visible_edges``):
    a refused candidate's verdict reads them and its polish on the plane starts from them, rendered once."""
    key = (pose.R.tobytes(), pose.t_mm.tobytes(), intr, size)
    return _SHOWN.get(bank, key, lambda: visible_edges(bank.vertices_mm, bank.faces, crease_edges_of(bank),
                                                       pose, intr, size))
