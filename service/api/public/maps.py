"""A map as the API shows it (its view, service/maps/view.py, with its latest validation) and the list."""

from __future__ import annotations

from typing import TYPE_CHECKING

from pydantic import BaseModel, Field

from service.api.public.validations import ValidationSummaryPublic, validation_summary_public
from service.maps.view import MapView, map_view

if TYPE_CHECKING:
    from service.calibration_service import Records


class MapSummaryPublic(BaseModel):
    id: int
    sweep_id: int | None = None
    harmonic_order: int
    method: str
    created_at: str


class MapPublic(MapView):
    """GET /maps/{id}: the map (service/maps/view.py) with its latest validation."""

    validation: ValidationSummaryPublic | None = Field(
        None, description="the latest validation in the drive's LUT mode (cells: GET /maps/{id}/validation)"
    )


def map_public(records: Records, map_id: int, smooth: bool = False) -> MapPublic | None:
    view = map_view(records, map_id, smooth)
    if view is None:
        return None
    validation = records.latest_validation(map_id)
    return MapPublic(**dict(view), validation=validation_summary_public(validation) if validation else None)


def map_summaries(records: Records, limit: int) -> list[MapSummaryPublic]:
    return [MapSummaryPublic(**row) for row in records.list_maps(limit)]
