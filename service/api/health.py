"""``GET /health``: answers at once, whatever builds and estimates are running; 503 with one sentence
while the store (a shared Redis) cannot be reached, 200 again as soon as it can."""

from __future__ import annotations

from importlib.metadata import PackageNotFoundError, version

from fastapi import APIRouter, Request

from service.api import error_responses
from service.errors import StoreUnavailableError
from service.schemas import Health

try:
    VERSION = version("posecell")
except PackageNotFoundError:  # a source tree that was never installed: its pyproject says which version
    import tomllib
    from pathlib import Path

    _pyproject = Path(__file__).resolve().parents[2] / "pyproject.toml"
    VERSION = "0+unknown"
    if _pyproject.exists():
        VERSION = tomllib.loads(_pyproject.read_text())["project"]["version"]

router = APIRouter(tags=["health"])


@router.get("/health", response_model=Health, responses=error_responses(503))
def health(request: Request) -> Health:  # sync: a store ping must not hold the event loop
    store = request.app.state.store
    problem = store.ping()
    if problem is not None:
        raise StoreUnavailableError(problem)
    ready = request.app.state.warm.is_set()
    return Health(status="ok", version=VERSION, store=store.kind, ready=ready,
                  state="ready" if ready else "starting")
