"""FastAPI application: the routes, the dashboard's static files, Plotly.js from the plotly package."""
from __future__ import annotations

import contextlib
from pathlib import Path

import plotly
from fastapi import FastAPI
from fastapi.exceptions import RequestValidationError
from fastapi.responses import FileResponse
from fastapi.staticfiles import StaticFiles

from service import __version__
from service.api.body_limit import BodySizeLimit
from service.api.errors import request_validation_error
from service.api.routes import ROUTERS
from service.calibration_service import CalibrationService

WEB_DIR = Path(__file__).resolve().parent.parent.parent / "web"
PLOTLY_JS = Path(plotly.__file__).resolve().parent / "package_data" / "plotly.min.js"


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

    app = FastAPI(title="ripplecal", version=__version__, lifespan=lifespan,
                  description="Hardware-in-the-loop calibration of torque-harmonic compensation for PMSM drives.")
    app.state.service = service
    for router in ROUTERS:
        app.include_router(router)
    app.add_exception_handler(RequestValidationError, request_validation_error)
    app.add_middleware(BodySizeLimit, max_body_bytes=service.settings.server.max_body_bytes)

    @app.get("/", include_in_schema=False)
    def index() -> FileResponse:
        return FileResponse(WEB_DIR / "index.html")

    @app.get("/vendor/plotly.min.js", include_in_schema=False)
    def plotly_js() -> FileResponse:
        return FileResponse(PLOTLY_JS, media_type="application/javascript")

    app.mount("/static", StaticFiles(directory=WEB_DIR), name="static")
    return app
