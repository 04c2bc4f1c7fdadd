"""The app factory: ``create_app(settings) -> FastAPI``.

The lifespan owns the two long-lived objects, the ``Store`` (template cache) and the ``Builder``
(template-build process pool), and re-queues builds a previous run left unfinished. Routers live
in ``service.api``; every error is written as ``{"detail": "<one sentence>."}`` (``service.errors``).
Around the routes (``service.middleware``): request ids, access logs and metrics; the optional API
key; the upload size limit. Run it with ``python -m service serve`` (JSON logs, metrics of all
workers) or ``uvicorn 'service.main:create_app' --factory``.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager

from fastapi import FastAPI
from fastapi.responses import JSONResponse
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from service import monitoring, ui
from service.api import cameras, error_responses, estimate, grasps, health, metrics, models, references
from service.api.deps import ApiKeyDocumented
from service.api.health import VERSION
from service.errors import install_handlers, sentence
from service.jobs import make_builder
from service.jobs.calibrations import Calibrator
from service.logs import capture_warnings
from service.middleware import ApiKeyGuard, RequestContext
from service.settings import Settings
from service.stores import open_store
from service.vision import pipeline, threads

log = logging.getLogger("service")

FORM_OVERHEAD_BYTES = 1 << 20  # room for the small form parts and multipart framing next to the file


class _BodyTooLarge(StarletteHTTPException):
    """Raised while the body is being received (an HTTPException, so FastAPI passes it through)."""


class UploadLimit:
    """Stops reading a request body, with 413, as soon as it exceeds the route's limit.

    The limit is the route's file limit plus ``FORM_OVERHEAD_BYTES``; a ``Content-Length`` over it
    is refused before a byte is read. The exact per-file limit is checked again as the handler
    reads the part (``deps.read_upload``).
    """

    def __init__(self, app: ASGIApp, settings: Settings) -> None:
        self.app = app
        self.settings = settings

    def _limit(self, scope: Scope) -> tuple[int, str]:
        path = scope.get("path", "")
        if scope.get("method") == "POST" and path.rstrip("/") == "/models":
            return self.settings.max_mesh_bytes + FORM_OVERHEAD_BYTES, "mesh upload (POSE_MAX_MESH_BYTES)"
        if scope.get("method") == "POST" and path.rstrip("/").endswith(("/estimate", "/references")):
            return self.settings.max_image_bytes + FORM_OVERHEAD_BYTES, "image upload (POSE_MAX_IMAGE_BYTES)"
        return FORM_OVERHEAD_BYTES, "request body"

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        limit, what = self._limit(scope)
        detail = sentence(f"The request body is larger than the {limit:,}-byte limit for a {what}; "
                          "send a smaller file")
        length = dict(scope.get("headers") or []).get(b"content-length")
        if length is not None and length.isdigit() and int(length) > limit:
            await JSONResponse({"detail": detail}, status_code=413, headers={"Connection": "close"})(
                scope, receive, send)
            return
        total = 0

        async def limited_receive() -> Message:
            nonlocal total
            message = await receive()
            if message["type"] == "http.request":
                total += len(message.get("body", b""))
                if total > limit:
                    raise _BodyTooLarge(413, detail, headers={"Connection": "close"})
            return message

        await self.app(scope, limited_receive, send)


def _warm_up(done: threading.Event) -> None:
    t0 = time.perf_counter()
    try:
        out = pipeline.warm_up()
    except Exception:  # a failed warm-up must not take the service down; the first estimate pays instead
        log.exception("warm-up failed")
        return
    finally:
        done.set()
    log.info("warm-up done in %d ms (synthetic part found: %s)", (time.perf_counter() - t0) * 1000, out.found)


def create_app(settings: Settings | None = None) -> FastAPI:
    settings = settings or Settings()

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        capture_warnings()  # uvicorn has applied logs.logging_config in this process by now
        threads.configure(settings.threads)
        if not settings.shared_store:
            settings.cache_dir.mkdir(parents=True, exist_ok=True)
        store = open_store(settings.store_location, bank_cache_mb=settings.bank_cache_mb)
        builder = make_builder(settings)
        calibrator = Calibrator(store, settings.build_lease_s, settings.plane_calibration_scenes)
        app.state.store, app.state.builder, app.state.calibrator = store, builder, calibrator
        builder.resume(store)
        calibrator.resume()  # calibrations a stop or crash ended
        warm = threading.Thread(target=_warm_up, args=(app.state.warm,), name="warm-up") \
            if settings.warm_up else None
        if warm is not None:
            warm.start()
        else:
            app.state.warm.set()
        try:
            yield
        finally:  # uvicorn gets here once in-flight requests are answered (graceful shutdown)
            if warm is not None:  # numba threads still running at interpreter exit abort the process
                warm.join()
            builder.shutdown()  # running builds go back to "queued": the next start-up resumes them
            calibrator.shutdown()  # a calibration stays due in the store: the next start-up resumes it
            store.close()
            monitoring.process_stopped()

    app = FastAPI(
        title="posecell", version=VERSION, lifespan=lifespan,
        docs_url=None, redoc_url=None,  # served from the package by service.ui (no CDN)
        description="6D pose of a CAD part from one camera image: borderline templates, directional "
                    "chamfer matching, LM refinement. Lengths in mm, angles in degrees, poses T_cam_obj "
                    "(OpenCV camera frame).",
    )
    app.state.settings = settings
    app.state.warm = threading.Event()  # set once the warm-up has compiled the kernels (GET /health: ready)
    install_handlers(app)
    # add_middleware puts each one outside the ones before: RequestContext ends up outermost
    app.add_middleware(UploadLimit, settings=settings)
    app.add_middleware(ApiKeyGuard, api_key=settings.api_key)
    app.add_middleware(RequestContext)
    for module in (health, metrics):
        app.include_router(module.router)
    for module in (models, grasps, references, estimate, cameras):  # behind the optional API key
        app.include_router(module.router, dependencies=[ApiKeyDocumented],
                           responses=error_responses(401))
    ui.install(app)  # /ui, /docs, /redoc and their files
    return app
