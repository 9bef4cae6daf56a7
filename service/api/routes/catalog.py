"""What the service offers, read from its registries: identification methods (with the JSON schema
of their options) and export formats. The dashboard and the CLI fill their choices from here."""

from __future__ import annotations

from typing import Any

from fastapi import APIRouter
from pydantic import BaseModel

from service.identification.registry import METHODS
from service.maps.lut_export import EXPORT_FORMATS

router = APIRouter(prefix="/api/v1", tags=["catalog"])


class MethodPublic(BaseModel):
    name: str
    display_name: str
    summary: str
    options_schema: dict[str, Any]


class ExportFormatPublic(BaseModel):
    name: str
    display_name: str
    media_type: str
    extension: str


@router.get("/methods", response_model=list[MethodPublic])
def list_methods() -> list[MethodPublic]:
    return [
        MethodPublic(
            name=m.name,
            display_name=m.display_name,
            summary=m.summary,
            options_schema=m.options_model.model_json_schema(),
        )
        for m in METHODS.values()
    ]


@router.get("/export-formats", response_model=list[ExportFormatPublic])
def list_export_formats() -> list[ExportFormatPublic]:
    return [
        ExportFormatPublic(name=f.name, display_name=f.display_name, media_type=f.media_type, extension=f.extension)
        for f in EXPORT_FORMATS.values()
    ]
