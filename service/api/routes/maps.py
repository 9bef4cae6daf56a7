"""Maps: the compensation over a sweep's grid, its exports and its download into the drive."""
from __future__ import annotations

from typing import Literal

from fastapi import APIRouter, HTTPException, Query, status
from fastapi.responses import PlainTextResponse

from service.api.deps import OperatorDep, ResourceId, ServiceDep
from service.api.errors import error_responses, validation_error
from service.api.refusals import unprocessable
from service.bench import BenchError
from service import lut_download
from service.lut_export import EXPORT_FORMATS, export_map
from service.public import LutDownloadPublic, MapPublic, MapSummaryPublic, map_public, map_summaries

router = APIRouter(prefix="/api/v1", tags=["maps"])


@router.get("/maps", response_model=list[MapSummaryPublic])
def list_maps(service: ServiceDep, limit: int = Query(50, ge=1, le=1000)) -> list[MapSummaryPublic]:
    return map_summaries(service.storage, limit)


@router.get("/maps/{map_id}", response_model=MapPublic, responses=error_responses(404))
def get_map(map_id: ResourceId, service: ServiceDep) -> MapPublic:
    m = map_public(service.storage, map_id)
    if m is None:
        raise HTTPException(status.HTTP_404_NOT_FOUND, f"map {map_id} does not exist")
    return m


_EXPORT_CONTENT = {media: {"schema": {"type": "object" if media == "application/json" else "string"}}
                   for media in {f.media_type for f in EXPORT_FORMATS.values()}}
ExportFormatName = Literal[tuple(EXPORT_FORMATS)]


@router.get("/maps/{map_id}/export",
            responses={200: {"description": "the map as a file", "content": _EXPORT_CONTENT}, **error_responses(404)})
def export(map_id: ResourceId, service: ServiceDep,
           format: ExportFormatName = Query("csv", description=" | ".join(
               f"{f.name}: {f.display_name}" for f in EXPORT_FORMATS.values()))) -> PlainTextResponse:
    m = _map_dict(service, map_id)
    fmt = EXPORT_FORMATS[format]
    return PlainTextResponse(export_map(m, format), media_type=fmt.media_type,
                             headers={"Content-Disposition": f'attachment; filename="ripplecal_map{map_id}.{fmt.extension}"'})


@router.post("/maps/{map_id}/download", response_model=LutDownloadPublic,
             responses=error_responses(401, 403, 404, 409, 502))
def download_map(map_id: ResourceId, service: ServiceDep, _: OperatorDep,
                 force: bool = Query(False, description="load a partial map (some cells not ok: no injection "
                                                        "there); without it such a map is refused with 409")
                 ) -> LutDownloadPublic:
    """The map's LUT image into the drive (0x2001, segmented SDO), its CRC-32 and map id read back.
    422: no ok cell (or not an image); 409: partial map without force, or the bench is busy / not reached."""
    try:
        return lut_download.download_map(service.storage, service.bench, map_id, force)
    except lut_download.MapNotFound as exc:
        raise HTTPException(status.HTTP_404_NOT_FOUND, str(exc)) from None
    except lut_download.LutRefused as exc:
        raise unprocessable(validation_error(["path", "map_id"], str(exc))) from None
    except (lut_download.PartialMap, BenchError) as exc:
        raise HTTPException(status.HTTP_409_CONFLICT, str(exc)) from None
    except Exception as exc:   # SDO abort / timeout: the drive refused or did not answer
        raise HTTPException(status.HTTP_502_BAD_GATEWAY, f"drive refused the LUT: {exc}") from None


def _map_dict(service, map_id: int) -> dict:
    """The map as the exporters read it (its Public shape, as a dict)."""
    m = map_public(service.storage, map_id)
    if m is None:
        raise HTTPException(status.HTTP_404_NOT_FOUND, f"map {map_id} does not exist")
    return m.model_dump()
