"""FastAPI application: the routes, the dashboard's static files, Plotly.js from the plotly package,
/docs with its assets from the fastapi-offline package (benches are offline: no CDN)."""

from __future__ import annotations

import contextlib
from pathlib import Path

import fastapi_offline
import plotly
from fastapi import FastAPI
from fastapi.exceptions import RequestValidationError
from fastapi.openapi.docs import get_swagger_ui_html, get_swagger_ui_oauth2_redirect_html
from fastapi.responses import FileResponse, HTMLResponse
from fastapi.staticfiles import StaticFiles

from service import __version__
from service.api.auth_throttle import AuthThrottle
from service.api.body_limit import BodySizeLimit
from service.api.errors import (
    ANSWERED_KINDS,
    EVERY_ROUTE,
    ErrorAnswers,
    request_validation_error,
    service_error,
    value_error,
)
from service.api.routes import ROUTERS
from service.calibration_service import CalibrationService

WEB_DIR = Path(__file__).resolve().parent.parent.parent / "web"
PLOTLY_JS = Path(plotly.__file__).resolve().parent / "package_data" / "plotly.min.js"
# swagger-ui-bundle.js, swagger-ui.css, redoc.standalone.js, favicon.png (fastapi-offline ships them, kept current)
DOCS_ASSETS = Path(fastapi_offline.__file__).resolve().parent / "static"
DOCS_ASSETS_URL = "/docs-assets"


def create_app(service: CalibrationService, manage_lifecycle: bool = True) -> FastAPI:
    @contextlib.asynccontextmanager
    async def lifespan(app: FastAPI):
        if manage_lifecycle:
            service.start()
        try:
            yield
        finally:
            if manage_lifecycle:
                service.stop()

    app = FastAPI(
        title="ripplecal",
        version=__version__,
        lifespan=lifespan,
        docs_url=None,
        redoc_url=None,
        description="Hardware-in-the-loop calibration of torque-harmonic compensation for PMSM drives.",
    )
    app.state.service = service
    server = service.settings.server
    app.state.auth_throttle = AuthThrottle(server.auth_max_failures, server.auth_failure_window_s)
    for router in ROUTERS:
        app.include_router(router, responses=EVERY_ROUTE)  # every route documents 500 and 503
    app.add_exception_handler(RequestValidationError, request_validation_error)
    # the one place a refusal becomes an answer: routes hold no `try` (service/errors.py declares the statuses)
    for kind in ANSWERED_KINDS:
        app.add_exception_handler(kind, service_error)
    app.add_exception_handler(ValueError, value_error)
    app.add_middleware(BodySizeLimit, max_body_bytes=service.settings.server.max_body_bytes)
    # added last: outermost, so an error anywhere below (the body limit too) is a JSON answer, never plain text
    app.add_middleware(ErrorAnswers)

    @app.get("/", include_in_schema=False)
    def index() -> FileResponse:
        return FileResponse(WEB_DIR / "index.html")

    @app.get("/vendor/plotly.min.js", include_in_schema=False)
    def plotly_js() -> FileResponse:
        return FileResponse(PLOTLY_JS, media_type="application/javascript")

    app.mount("/static", StaticFiles(directory=WEB_DIR), name="static")
    _add_docs(app)
    return app


def _add_docs(app: FastAPI) -> None:
    """/docs (Swagger UI) as FastAPI serves it, its assets from DOCS_ASSETS. No /redoc: ReDoc's page
    loads its logo from a CDN."""
    app.mount(DOCS_ASSETS_URL, StaticFiles(directory=DOCS_ASSETS), name="docs-assets")
    favicon = f"{DOCS_ASSETS_URL}/favicon.png"

    @app.get("/docs", include_in_schema=False)
    def swagger_ui() -> HTMLResponse:
        return get_swagger_ui_html(
            openapi_url=app.openapi_url,
            title=f"{app.title} - API",
            oauth2_redirect_url=app.swagger_ui_oauth2_redirect_url,
            swagger_js_url=f"{DOCS_ASSETS_URL}/swagger-ui-bundle.js",
            swagger_css_url=f"{DOCS_ASSETS_URL}/swagger-ui.css",
            swagger_favicon_url=favicon,
            # no validator badge: it would call validator.swagger.io
            swagger_ui_parameters={"validatorUrl": None},
        )

    @app.get(app.swagger_ui_oauth2_redirect_url, include_in_schema=False)
    def swagger_ui_redirect() -> HTMLResponse:
        return get_swagger_ui_oauth2_redirect_html()
