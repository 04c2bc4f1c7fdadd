"""Dependencies as ``Annotated`` aliases, so a route reads like prose and the 404/409 rules live here.

``StoreDep``, ``SettingsDep``, ``BuilderDep``: the app-wide objects the lifespan created.
``ModelRecord``: the model named by the ``model_id`` path parameter, or 404.
``ReadyModel``: that model with its template bank loaded, or 404 / 409 (not ready) / 409 (failed).
``ApiKeyDocumented``: the ``X-API-Key`` header in the OpenAPI schema of the routes that need it.
"""

from __future__ import annotations

import json
import math
import re
from dataclasses import dataclass
from typing import Annotated, Any, TypeVar

from fastapi import Depends, Request, Security, UploadFile
from fastapi.security import APIKeyHeader
from pydantic import BaseModel, ValidationError

from service.builder import Builder
from service.errors import (
    BuildFailedError,
    NotFoundError,
    NotReadyError,
    TooLargeError,
    UnprocessableError,
    clause,
    validation_sentence,
)
from service.settings import Settings
from service.store import Store
from service.vision.bank import TemplateBank

CHUNK_BYTES = 1 << 20


def get_store(request: Request) -> Store:
    return request.app.state.store


def get_settings(request: Request) -> Settings:
    return request.app.state.settings


def get_builder(request: Request) -> Builder:
    return request.app.state.builder


StoreDep = Annotated[Store, Depends(get_store)]
SettingsDep = Annotated[Settings, Depends(get_settings)]
BuilderDep = Annotated[Builder, Depends(get_builder)]


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
    mid, status = record["id"], record["status"]
    if status == "failed":
        reason = clause(record.get("error") or "unknown reason")
        raise BuildFailedError(f"Model '{mid}' failed to build: {reason}; fix the mesh or the template "
                               "options and upload it again")
    bank = store.bank(mid) if status == "ready" else None
    if bank is None:
        done = 100 * float(record.get("progress") or 0.0)
        raise NotReadyError(f"Model '{mid}' is not ready yet (template build {status}, {done:.0f}% done); "
                            f"retry after Retry-After seconds or poll GET /models/{mid} until it is ready")
    return Loaded(record, bank)


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


M = TypeVar("M", bound=BaseModel)


def _finite(v: Any) -> bool:
    if isinstance(v, float):
        return math.isfinite(v)
    if isinstance(v, dict):
        return all(_finite(x) for x in v.values())
    if isinstance(v, list):
        return all(_finite(x) for x in v)
    return True


MAX_JSON_DEPTH = 16  # the deepest any part's JSON needs is 2 (distance_range_mm, dist)
_JSON_STRING = re.compile(r'"(?:[^"\\]|\\.)*"')
_NOT_BRACKET = re.compile(r"[^\[\]{}]+")
_JSON_TYPES = {dict: "an object", list: "an array", str: "a string", bool: "a boolean", int: "a number",
               float: "a number", type(None): "null"}


def json_depth(text: str) -> int:
    """How deeply ``text``'s arrays and objects nest (brackets inside strings do not count); linear."""
    depth = deepest = 0
    for ch in _NOT_BRACKET.sub("", _JSON_STRING.sub("", text)):
        depth += 1 if ch in "[{" else -1
        deepest = max(deepest, depth)
    return deepest


def parse_json_object(text: str | None, what: str) -> dict[str, Any]:
    """A form part holding a JSON object -> dict; 422 (one sentence) on bad JSON, non-objects, NaN or
    nesting deeper than ``MAX_JSON_DEPTH`` (checked before parsing: 100,000 brackets made json.loads
    raise RecursionError, a 500)."""
    if text is None or not text.strip():
        return {}
    if json_depth(text) > MAX_JSON_DEPTH:
        raise UnprocessableError(f"The {what} part nests arrays or objects more than {MAX_JSON_DEPTH} levels "
                                 "deep; send a flat JSON object such as {\"key\": value}")
    try:
        value = json.loads(text)
    except json.JSONDecodeError as e:
        raise UnprocessableError(f"The {what} part is not valid JSON ({e.msg} at character {e.pos}); send a "
                                 "JSON object such as {\"key\": value}") from e
    except RecursionError as e:  # a guard behind the depth check
        raise UnprocessableError(f"The {what} part nests too deeply; send a flat JSON object") from e
    if not isinstance(value, dict):
        got = _JSON_TYPES.get(type(value), type(value).__name__)
        raise UnprocessableError(f"The {what} part must be a JSON object, not {got}; send {{\"key\": value, "
                                 "...}} or leave the part out")
    if not _finite(value):
        raise UnprocessableError(f"The {what} part contains NaN or Infinity; send finite numbers only")
    return value


def parse_json_part(text: str | None, model: type[M], what: str) -> M:
    """A form part holding JSON -> the wire model; 422 with one sentence naming the first problem."""
    try:
        return model.model_validate(parse_json_object(text, what))
    except ValidationError as e:
        raise UnprocessableError(validation_sentence(e.errors(), what=what)) from e
