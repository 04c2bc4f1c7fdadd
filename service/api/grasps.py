"""Grasps: ``PUT/GET /models/{id}/grasps``, named gripper poses in the model frame (``T_obj_grasp``).

Every found estimate of the model returns them placed where the part is (``service.cell.place_grasps``).
"""

from __future__ import annotations

from fastapi import APIRouter

from service.api import error_responses
from service.api.deps import ModelRecord, StoreDep
from service.errors import UnprocessableError
from service.schemas import GraspSpec

router = APIRouter(tags=["models"])


@router.put("/models/{model_id}/grasps", response_model=list[GraspSpec], responses=error_responses(404, 422))
def put_grasps(record: ModelRecord, grasps: list[GraspSpec], store: StoreDep) -> list[GraspSpec]:
    """Replace the model's grasps (an empty list removes them). Names must be unique."""
    seen: set[str] = set()
    for g in grasps:
        if g.name in seen:
            raise UnprocessableError(f"Two grasps are named '{g.name}'; give every grasp of a model its own "
                                     "name")
        seen.add(g.name)
    store.put_grasps(record["id"], [g.model_dump() for g in grasps])
    return grasps


@router.get("/models/{model_id}/grasps", response_model=list[GraspSpec], responses=error_responses(404, 422))
def get_grasps(record: ModelRecord, store: StoreDep) -> list[GraspSpec]:
    return [GraspSpec.model_validate(g) for g in store.grasps(record["id"])]
