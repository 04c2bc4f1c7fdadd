"""Dependencies as ``Annotated`` aliases, so a route reads like prose and the 404/409 rules live here.

``StoreDep``, ``SettingsDep``, ``BuilderDep``: the app-wide objects the lifespan created.
``ModelRecord``: the model named by the ``model_id`` path parameter, or 404.
``ReadyModel``: that model with its template bank loaded, or 404 / 409 (not ready) / 409 (failed).
``ApiKeyDocumented``: the ``X-API-Key`` header in the OpenAPI schema of the routes that need it.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Annotated, Any

from fastapi import Depends, Request, Security, UploadFile
from fastapi.security import APIKeyHeader

from service.errors import (
    NotFoundError,
    TooLargeError,
)
from service.jobs.calibrations import Calibrator
from service.jobs.local import Builder
from service.settings import Settings
from service.stores.base import Store
from service.vision.bank import TemplateBank

CHUNK_BYTES = 1 << 20


def get_store(request: Request) -> Store:
    return request.app.state.store


def get_settings(request: Request) -> Settings:
    return request.app.state.settings


def get_builder(request: Request) -> Builder:
    return request.app.state.builder


def get_calibrator(request: Request) -> Calibrator:
    return request.app.state.calibrator


StoreDep = Annotated[Store, Depends(get_store)]
SettingsDep = Annotated[Settings, Depends(get_settings)]
BuilderDep = Annotated[Builder, Depends(get_builder)]
CalibratorDep = Annotated[Calibrator, Depends(get_calibrator)]


MAX_ID_ECHO_CHARS = 64  # model ids are 20 hex characters; a longer one is not echoed back whole


def get_record(model_id: str, store: StoreDep) -> dict[str, Any]:
    if len(model_id) > MAX_ID_ECHO_CHARS:
        raise NotFoundError(f"No model has an id of {len(model_id):,} characters (ids are 20 hexadecimal "
                            "characters); list the models with GET /models or upload one with POST /models")
    record = store.get(model_id)
    if record is None:
        raise NotFoundError(f"No model has id '{model_id}'; list the models with GET /models or upload one "
                            "with POST /models")
    return record


ModelRecord = Annotated[dict[str, Any], Depends(get_record)]


@dataclass(frozen=True)
class Loaded:
    record: dict[str, Any]
    bank: TemplateBank

    @property
    def id(self) -> str:
        return self.record["id"]


def get_ready_model(record: ModelRecord, store: StoreDep) -> Loaded:
    return Loaded(record, store.ready_bank(record))


ReadyModel = Annotated[Loaded, Depends(get_ready_model)]


# The key is checked by ``service.middleware.ApiKeyGuard`` before a body is read; this dependency
# only puts the header and its security scheme into the OpenAPI schema of the protected routes.
API_KEY_SCHEME = APIKeyHeader(
    name="X-API-Key", scheme_name="APIKey", auto_error=False,
    description="required on every route but /health and /metrics when the service has POSE_API_KEY set")
ApiKeyDocumented = Security(API_KEY_SCHEME)


# --- request bodies -------------------------------------------------------------------------------

async def read_upload(upload: UploadFile, limit: int, what: str, setting: str) -> bytes:
    """The uploaded part's bytes, read in chunks; 413 as soon as they exceed ``limit``."""
    if upload.size is not None and upload.size > limit:
        raise TooLargeError(_too_large(what, limit, setting))
    chunks, total = [], 0
    while chunk := await upload.read(CHUNK_BYTES):
        total += len(chunk)
        if total > limit:
            raise TooLargeError(_too_large(what, limit, setting))
        chunks.append(chunk)
    return b"".join(chunks)


def _too_large(what: str, limit: int, setting: str) -> str:
    return f"The {what} is larger than the limit of {limit:,} bytes ({setting}); send a smaller file"
