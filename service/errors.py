"""The service's errors: one family, each a status code and one sentence a person can act on.

::

    ServiceError                     500  base: ``status_code``, ``detail`` (one sentence), ``headers``
    (Starlette's 400 from the multipart parser is answered as a sentence too, naming the parser's reason)
    ├── UnauthorizedError            401  POSE_API_KEY is set and X-API-Key is missing or wrong
    ├── NotFoundError                404  unknown model id, template index out of range
    ├── ConflictError                409  the model exists but cannot serve the request (yet)
    │   ├── NotReadyError            409  template build queued or running; sends ``Retry-After``
    │   └── BuildFailedError         409  template build failed; the detail says why
    ├── TooLargeError                413  upload over a size limit (bytes or pixels)
    ├── UnsupportedMediaError        415  bytes that are not a mesh / image format we read
    ├── UnprocessableError           422  well-formed request with unusable content (bad JSON,
    │                                     fx <= 0, NaN, a mesh without faces, an empty file, ...)
    └── StoreUnavailableError        503  the shared store (Redis) cannot be reached; sends ``Retry-After``

``install_handlers(app)`` makes EVERY error response ``{"detail": "<one sentence>."}``: these
errors, FastAPI/pydantic request validation errors, Starlette's HTTP errors (unknown route 404,
405) and unexpected exceptions (500).
"""

from __future__ import annotations

import logging
import re
from collections.abc import Mapping, Sequence
from typing import Any

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from starlette.exceptions import HTTPException as StarletteHTTPException

log = logging.getLogger("service")

RETRY_AFTER_S = 2  # what a 409 "not ready" tells the client to wait before asking again


def sentence(text: str) -> str:
    """One line, ending with exactly one full stop (or ? / !); a first plain word is capitalised."""
    s = re.sub(r"\s+", " ", str(text)).strip().rstrip(".;:, ")
    if not s:
        s = "Something went wrong"
    if s.split(" ", 1)[0].isalpha():  # not identifiers such as reference_distance_mm
        s = s[0].upper() + s[1:]
    return s + ("" if s[-1] in "?!" else ".")


def clause(text: str) -> str:
    """``text`` as a clause to embed in a sentence: one line, no final full stop."""
    return re.sub(r"\s+", " ", str(text)).strip().rstrip(".;:, ")


class ServiceError(Exception):
    status_code = 500

    def __init__(self, detail: str, *, headers: Mapping[str, str] | None = None) -> None:
        self.detail = sentence(detail)
        self.headers = dict(headers or {})
        super().__init__(self.detail)


class UnauthorizedError(ServiceError):
    status_code = 401


class NotFoundError(ServiceError):
    status_code = 404


class ConflictError(ServiceError):
    status_code = 409


class NotReadyError(ConflictError):
    def __init__(self, detail: str, *, retry_after_s: int = RETRY_AFTER_S) -> None:
        super().__init__(detail, headers={"Retry-After": str(int(retry_after_s))})


class BuildFailedError(ConflictError):
    pass


class TooLargeError(ServiceError):
    status_code = 413


class UnsupportedMediaError(ServiceError):
    status_code = 415


class UnprocessableError(ServiceError):
    status_code = 422


class StoreUnavailableError(ServiceError):
    status_code = 503

    def __init__(self, detail: str, *, retry_after_s: int = RETRY_AFTER_S) -> None:
        super().__init__(detail, headers={"Retry-After": str(int(retry_after_s))})


# --- validation errors -> one sentence ------------------------------------------------------------

_WHERE = {"body": "form part", "path": "path parameter", "query": "query parameter", "header": "header",
          "cookie": "cookie"}


def _loc_name(loc: Sequence[Any]) -> str:
    parts = [str(p) for p in loc]
    return ".".join(parts) if parts else "value"


def _msg(err: Mapping[str, Any]) -> str:
    msg = clause(err.get("msg", "is invalid"))
    for prefix in ("Value error, ", "Assertion failed, "):
        if msg.startswith(prefix):
            msg = msg[len(prefix):]
    return msg


def validation_sentence(errors: Sequence[Mapping[str, Any]], *, what: str | None = None,
                        body: str = _WHERE["body"]) -> str:
    """pydantic/FastAPI error list -> one sentence naming the first problem (and how many more).

    ``what`` names the JSON document the errors are about (e.g. "camera"); without it the first
    element of each ``loc`` says where (body/path/query); ``body`` is what a "body" is called (a form
    part, or a JSON body's field).
    """
    if not errors:
        return sentence(f"The {what or 'request'} is invalid; check it against the API documentation")
    err = errors[0]
    loc = list(err.get("loc", ()))
    if what is None:
        where = (body if str(loc[0]) == "body" else _WHERE.get(str(loc[0]), "field")) if loc else "request"
        loc = loc[1:]
        subject = f"{where} '{_loc_name(loc)}'" if loc else f"request {where.removesuffix(' field')}"
    else:
        subject = f"{what} field '{_loc_name(loc)}'" if loc else what
    more = f" (and {len(errors) - 1} more problem{'s' if len(errors) > 2 else ''})" if len(errors) > 1 else ""
    if err.get("type") == "missing":
        # an empty form field reaches FastAPI as no field at all: say both
        gone = "missing or empty" if subject.startswith("form part") else "missing"
        text = f"The {subject} is {gone}{more}; add it and send the request again"
    else:
        text = f"The {subject} is invalid: {_msg(err)}{more}; fix it and send the request again"
    return sentence(text)


# --- handlers --------------------------------------------------------------------------------------

def _json(status: int, detail: str, headers: Mapping[str, str] | None = None) -> JSONResponse:
    return JSONResponse({"detail": sentence(detail)}, status_code=status, headers=dict(headers or {}))


async def _service_error(request: Request, exc: ServiceError) -> JSONResponse:
    return _json(exc.status_code, exc.detail, exc.headers)


async def _validation_error(request: Request, exc: RequestValidationError) -> JSONResponse:
    json_body = request.headers.get("content-type", "").split(";")[0].strip() == "application/json"
    body = "JSON body field" if json_body else _WHERE["body"]
    return _json(422, validation_sentence(exc.errors(), body=body))


_METHODS = ("GET", "HEAD", "POST", "PUT", "PATCH", "DELETE", "OPTIONS")


def allowed_methods(request: Request) -> list[str]:
    """Every method some route of the app answers on this path (Starlette's 405 names only the first
    route's): each method is tried against the app's routes, as the router would."""
    from starlette.routing import Match

    routes = request.app.router.routes
    return [m for m in _METHODS
            if any(r.matches({**request.scope, "method": m})[0] == Match.FULL for r in routes)]


async def _http_error(request: Request, exc: StarletteHTTPException) -> JSONResponse:
    route = f"{request.method} {request.url.path}"
    headers = dict(getattr(exc, "headers", None) or {})
    if exc.status_code == 404 and exc.detail in (None, "Not Found"):
        detail = f"No endpoint matches {route}; see /docs for the API"
    elif exc.status_code == 405:
        allowed = allowed_methods(request)
        headers["Allow"] = ", ".join(allowed)
        detail = (f"Method {request.method} is not allowed on {request.url.path} (allowed: "
                  f"{', '.join(allowed)}); see /docs for the API")
    elif exc.status_code == 400:  # the multipart parser (python-multipart via Starlette) gave up
        why = clause(exc.detail) if isinstance(exc.detail, str) and exc.detail else "unreadable body"
        detail = (f"The request body could not be read as multipart/form-data ({why}); send the parts as "
                  "multipart/form-data, the file in its file part and every other part under 1 MB")
    elif isinstance(exc.detail, str) and exc.detail:
        detail = exc.detail
    else:
        detail = f"The request {route} failed with HTTP status {exc.status_code}"
    return _json(exc.status_code, detail, headers)


def unexpected_response(method: str, path: str, exc: BaseException) -> JSONResponse:
    """The 500 for an exception no handler knew: logged with its traceback, answered in one sentence."""
    log.error("unhandled error in %s %s", method, path, exc_info=exc)
    return _json(500, f"The service failed unexpectedly ({type(exc).__name__}); this is a bug, "
                      "please report it with the request that caused it")


async def _unexpected(request: Request, exc: Exception) -> JSONResponse:
    return unexpected_response(request.method, request.url.path, exc)


def install_handlers(app: FastAPI) -> None:
    app.add_exception_handler(ServiceError, _service_error)
    app.add_exception_handler(RequestValidationError, _validation_error)
    app.add_exception_handler(StarletteHTTPException, _http_error)
    app.add_exception_handler(Exception, _unexpected)
