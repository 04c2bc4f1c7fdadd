"""HTTP routers (health, models, grasps, references, estimate, cameras) and their dependencies (``deps``)."""

from typing import Any

from service.schemas import Error

_DESCRIPTIONS = {
    400: "The body is not readable multipart/form-data (the multipart parser's reason is in the detail).",
    401: "POSE_API_KEY is set and the X-API-Key header is missing or wrong.",
    404: "Unknown model id (or template index).",
    409: "Model not ready yet (with Retry-After), or its build failed (the detail says why); for a reference "
         "photo also: the model has the most it keeps.",
    413: "Upload over the size limit.",
    415: "The file is not a mesh / image format the service reads.",
    422: "Bad form part: bad JSON, out-of-range or implausible value, NaN, empty or unusable file.",
    503: "The shared store (Redis, POSE_STORE) cannot be reached (with Retry-After); retry when it is back.",
}


def error_responses(*codes: int) -> dict[int | str, dict[str, Any]]:
    """``responses=`` for a route: each listed status documented with the Error schema."""
    return {c: {"model": Error, "description": _DESCRIPTIONS[c]} for c in codes}
