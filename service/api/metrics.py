"""``GET /metrics``: Prometheus text format (what it contains: ``service.monitoring``)."""

from __future__ import annotations

from fastapi import APIRouter, Response

from service import monitoring
from service.api.deps import StoreDep

router = APIRouter(tags=["operations"])


@router.get("/metrics", response_class=Response, responses={200: {
    "content": {"text/plain": {}},
    "description": "request counts and latencies per route and status, estimate stage timings, builds "
                   "per status, cache size"}})
def metrics(store: StoreDep) -> Response:
    """Prometheus metrics of all the service's worker processes."""
    return Response(monitoring.exposition(store), media_type=monitoring.CONTENT_TYPE)
