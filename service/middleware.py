"""ASGI middleware around every request: its id, access log line and metrics; the optional API key.

``create_app`` stacks them, outermost first: ``RequestContext`` -> ``ApiKeyGuard`` -> the upload
limit -> the routes, so a refused key or an oversized body is logged, counted and carries its
``X-Request-ID`` like any other answer.
"""

from __future__ import annotations

import logging
import secrets
import time

from pydantic import SecretStr
from starlette.datastructures import Headers, MutableHeaders
from starlette.responses import JSONResponse
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from service import monitoring
from service.errors import UnauthorizedError, unexpected_response
from service.logs import REQUEST_ID_HEADER, request_id_from, request_id_var

access_log = logging.getLogger("service.access")

API_KEY_HEADER = "X-API-Key"
# Open with an API key set: the health check (Docker and orchestrators call it without credentials),
# the metrics (Prometheus scrapes without headers; neither shows model data) and the API docs.
OPEN_PATHS = frozenset({"/health", "/metrics", "/docs", "/docs/oauth2-redirect", "/redoc", "/openapi.json",
                        "/ui"})
# ... and the files those pages load (service/ui/static: Swagger UI, ReDoc; no model data). The
# operator page asks for the key itself and sends it with every API call.
OPEN_PREFIXES = ("/static/",)
# Polled every few seconds by machines: their access lines are debug, not info.
QUIET_PATHS = frozenset({"/health", "/metrics"})


def route_template(scope: Scope) -> str:
    """The path template of the route that answered, e.g. ``/models/{model_id}`` (call it after the app:
    FastAPI's router puts the route into the scope)."""
    return str(getattr(scope.get("route"), "path", None) or monitoring.UNMATCHED_ROUTE)


class RequestContext:
    """Gives each request an id (the client's ``X-Request-ID`` if usable), echoes it on the response,
    writes one access line and records the request metrics.

    An exception no handler turned into a response is answered here (500, one sentence), so that
    answer too has its id, its access line and its count.
    """

    def __init__(self, app: ASGIApp) -> None:
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        start = time.perf_counter()
        request_id = request_id_from(Headers(scope=scope).get(REQUEST_ID_HEADER))
        token = request_id_var.set(request_id)
        method, path = scope["method"], scope["path"]
        status = 500  # if the app fails before it starts a response
        started = False

        async def send_with_id(message: Message) -> None:
            nonlocal status, started
            if message["type"] == "http.response.start":
                started, status = True, int(message["status"])
                message["headers"] = list(message.get("headers", []))
                MutableHeaders(scope=message)[REQUEST_ID_HEADER] = request_id
            await send(message)

        monitoring.IN_PROGRESS.inc()
        try:
            await self.app(scope, receive, send_with_id)
        except Exception as exc:
            if started:  # half an answer is out: nothing better to do than let the server drop it
                raise
            await unexpected_response(method, path, exc)(scope, receive, send_with_id)
        finally:
            monitoring.IN_PROGRESS.dec()
            duration_s = time.perf_counter() - start
            route = route_template(scope)
            monitoring.REQUESTS.labels(method, route, str(status)).inc()
            monitoring.REQUEST_SECONDS.labels(method, route, str(status)).observe(duration_s)
            access_log.log(logging.DEBUG if path in QUIET_PATHS else logging.INFO,
                           "%s %s %d %.1f ms", method, path, status, 1000 * duration_s,
                           extra={"method": method, "path": path, "status": status,
                                  "duration_ms": round(1000 * duration_s, 3)})
            request_id_var.reset(token)


def api_key_matches(expected: SecretStr, presented: str | None) -> bool:
    """Constant-time comparison, so response times do not leak how much of a guess was right."""
    return presented is not None and secrets.compare_digest(presented.encode(),
                                                            expected.get_secret_value().encode())


class ApiKeyGuard:
    """With ``POSE_API_KEY`` set, answers 401 to any request outside ``OPEN_PATHS`` without that key
    in ``X-API-Key`` -- before its body is read, so an unauthenticated upload costs nothing."""

    def __init__(self, app: ASGIApp, api_key: SecretStr | None) -> None:
        self.app = app
        self.api_key = api_key

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if (scope["type"] != "http" or self.api_key is None or scope["path"] in OPEN_PATHS
                or scope["path"].startswith(OPEN_PREFIXES)):
            await self.app(scope, receive, send)
            return
        presented = Headers(scope=scope).get(API_KEY_HEADER)
        if api_key_matches(self.api_key, presented):
            await self.app(scope, receive, send)
            return
        error = UnauthorizedError(
            f"This service requires an API key; send it in the {API_KEY_HEADER} header" if presented is None
            else f"The API key in the {API_KEY_HEADER} header is not valid; send the key this service was "
                 "configured with")
        response = JSONResponse({"detail": error.detail}, status_code=error.status_code,
                                headers={"WWW-Authenticate": f'APIKey header="{API_KEY_HEADER}"'})
        await response(scope, receive, send)
