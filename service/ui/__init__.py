"""Pages for people, served by the service itself with no internet: the operator page ``/ui`` and the
API docs ``/docs`` (Swagger UI) and ``/redoc`` (ReDoc).

Everything they load comes from this package: ``index.html`` (the operator page, CSS and JS inline)
and ``static/`` (Swagger UI 5 and ReDoc 2, vendored from the npm packages ``swagger-ui-dist`` and
``redoc`` with their licences; FastAPI's defaults load them from a CDN, a blank page on a cell's
network). ``install(app)`` adds the routes; create the app with ``docs_url=None, redoc_url=None``.
"""

from __future__ import annotations

from pathlib import Path

from fastapi import FastAPI
from fastapi.openapi.docs import get_redoc_html, get_swagger_ui_html
from fastapi.responses import HTMLResponse
from fastapi.staticfiles import StaticFiles

HERE = Path(__file__).resolve().parent
STATIC_DIR = HERE / "static"
STATIC_URL = "/static"


def operator_page() -> str:
    return (HERE / "index.html").read_text(encoding="utf-8")


def install(app: FastAPI) -> None:
    """Mount ``/static`` and add ``/ui``, ``/docs`` and ``/redoc`` (none in the OpenAPI schema)."""
    app.mount(STATIC_URL, StaticFiles(directory=STATIC_DIR), name="static")
    title = app.title

    @app.get("/ui", include_in_schema=False, response_class=HTMLResponse)
    def ui() -> HTMLResponse:
        return HTMLResponse(operator_page())

    @app.get("/docs", include_in_schema=False)
    def swagger() -> HTMLResponse:
        return get_swagger_ui_html(
            openapi_url=app.openapi_url or "/openapi.json", title=f"{title} - API docs",
            swagger_js_url=f"{STATIC_URL}/swagger-ui/swagger-ui-bundle.js",
            swagger_css_url=f"{STATIC_URL}/swagger-ui/swagger-ui.css",
            swagger_favicon_url=f"{STATIC_URL}/swagger-ui/favicon-32x32.png")

    @app.get("/redoc", include_in_schema=False)
    def redoc() -> HTMLResponse:
        return get_redoc_html(
            openapi_url=app.openapi_url or "/openapi.json", title=f"{title} - API reference",
            redoc_js_url=f"{STATIC_URL}/redoc/redoc.standalone.js",
            redoc_favicon_url=f"{STATIC_URL}/swagger-ui/favicon-32x32.png", with_google_fonts=False)
