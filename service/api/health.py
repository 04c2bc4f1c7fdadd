"""``GET /health``: answers at once, whatever builds and estimates are running."""

from __future__ import annotations

from importlib.metadata import PackageNotFoundError, version

from fastapi import APIRouter

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


@router.get("/health", response_model=Health)
async def health() -> Health:
    return Health(status="ok", version=VERSION)
