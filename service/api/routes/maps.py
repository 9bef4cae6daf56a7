"""Maps: the compensation over a sweep's grid, its exports and its download into the drive."""

from __future__ import annotations

from typing import Literal

from fastapi import APIRouter, HTTPException, Query, status
from fastapi.responses import PlainTextResponse

from service.api.deps import OperatorDep, ResourceId, ServiceDep
from service.api.errors import error_responses
from service.api.public.jobs import JobPublic, job_public
from service.api.public.maps import MapPublic, MapSummaryPublic, map_public, map_summaries
from service.api.public.validations import ValidationPublic, validation_public
from service.api.refusals import refusals_at
from service.api.schemas import ValidationCreate
from service.maps.compare import MapComparison, compare_maps
from service.maps.lut_export import EXPORT_FORMATS, Interpolation, export_map
from service.runs import lut_download
from service.runs.refinement import RefineRequest

router = APIRouter(prefix="/api/v1", tags=["maps"])

# a view, never a change of the stored map: outlier cells carry their neighbours' fit (service/maps/quality.py)
SmoothQuery = Query(
    "none",
    description="outliers: outlier cells carry their ok neighbours' median theta, "
    "marked smoothed with their source (the stored map is not changed)",
)
Smooth = Literal["none", "outliers"]


@router.get("/maps", response_model=list[MapSummaryPublic])
def list_maps(service: ServiceDep, limit: int = Query(50, ge=1, le=1000)) -> list[MapSummaryPublic]:
    return map_summaries(service.records, limit)


@router.get("/maps/{map_id}", response_model=MapPublic, responses=error_responses(404))
def get_map(map_id: ResourceId, service: ServiceDep, smooth: Smooth = SmoothQuery) -> MapPublic:
    m = map_public(service.records, map_id, smooth=smooth == "outliers")
    if m is None:
        raise HTTPException(status.HTTP_404_NOT_FOUND, f"map {map_id} does not exist")
    return m


_EXPORT_CONTENT = {
    media: {"schema": {"type": "object" if media == "application/json" else "string"}}
    for media in {f.media_type for f in EXPORT_FORMATS.values()}
}
ExportFormatName = Literal[tuple(EXPORT_FORMATS)]


@router.get(
    "/maps/{map_id}/export",
    responses={200: {"description": "the map as a file", "content": _EXPORT_CONTENT}, **error_responses(404)},
)
def export(
    map_id: ResourceId,
    service: ServiceDep,
    format: ExportFormatName = Query(
        "csv", description=" | ".join(f"{f.name}: {f.display_name}" for f in EXPORT_FORMATS.values())
    ),
    smooth: Smooth = SmoothQuery,
) -> PlainTextResponse:
    m = _map_dict(service, map_id, smooth=smooth == "outliers")
    fmt = EXPORT_FORMATS[format]
    name = f"ripplecal_map{map_id}{'_smoothed' if smooth == 'outliers' else ''}.{fmt.extension}"
    return PlainTextResponse(
        export_map(m, format),
        media_type=fmt.media_type,
        headers={"Content-Disposition": f'attachment; filename="{name}"'},
    )


@router.get(
    "/maps/{map_id}/compare/{other_id}",
    response_model=MapComparison,
    responses=error_responses(404),
    dependencies=[refusals_at(["path", "other_id"])],
)
def compare(map_id: ResourceId, other_id: ResourceId, service: ServiceDep) -> MapComparison:
    """Map `other_id` (b) against map `map_id` (a) at the operating points both hold: delta gamma, delta
    delta, delta theta, and the suppression b's theta would reach on a's bench (a's measured S).
    A map compared with itself is allowed (zero deltas; the prediction is its measured suppression)."""
    return compare_maps(service.records, map_id, other_id)  # a map that does not exist: 404; other harmonics: 422


@router.post(
    "/maps/{map_id}/download",
    response_model=lut_download.LutDownload,
    responses=error_responses(401, 403, 404, 409, 502),
    dependencies=[refusals_at(["path", "map_id"])],
)
def download_map(
    map_id: ResourceId,
    service: ServiceDep,
    _: OperatorDep,
    force: bool = Query(
        False,
        description="load a map with holes (cells that would inject nothing); "
        "without it such a map is refused with 409",
    ),
    fill: bool = Query(
        True,
        description="the fill rule's entries of the cells that are not ok go in "
        "too (flagged filled in the image); false: only ok cells inject",
    ),
    interpolation: Interpolation | None = Query(
        None,
        description="what the drive interpolates between cells (default: the map's own, the one a refinement "
        "placed and validated it in, else the service's, drivers/lut_image.DEFAULT_INTERPOLATION)",
    ),
) -> lut_download.LutDownload:
    """The map's LUT image into the drive (0x2001, segmented SDO), its CRC-32 and map id read back.
    422: no ok cell (or not an image); 409: map with holes without force, or the bench is busy / not reached."""
    return service.download_map(map_id, force, fill=fill, interpolation=interpolation)


@router.post(
    "/maps/{map_id}/validate",
    status_code=status.HTTP_202_ACCEPTED,
    response_model=JobPublic,
    responses=error_responses(400, 401, 403, 404, 409, 413),
    dependencies=[refusals_at(["path", "map_id"])],
)
def validate_map(
    map_id: ResourceId, service: ServiceDep, _: OperatorDep, body: ValidationCreate | None = None
) -> JobPublic:
    """A job: the map's LUT into the drive, the drive in LUT mode, the h-th harmonic measured at every
    grid point and at the midpoints between them (uncompensated and with the drive's own feedforward)."""
    body = body or ValidationCreate()
    job_id = service.submit_validation(map_id, body.force, body.options, bench=body.bench)
    return job_public(service.records, service.records.get_job(job_id), service)


@router.post(
    "/maps/{map_id}/refine",
    status_code=status.HTTP_202_ACCEPTED,
    response_model=JobPublic,
    responses=error_responses(400, 401, 403, 404, 409, 413),
    dependencies=[refusals_at(["path", "map_id"], method_options=["body", "options"])],
)
def refine_map(map_id: ResourceId, service: ServiceDep, _: OperatorDep, body: RefineRequest | None = None) -> JobPublic:
    """A job (kind refinement, run as a sweep of that kind: pause, resume and cancel it there): validate
    the map in the drive's LUT mode, insert axis values where a point misses target_db, identify the new
    cells, validate again; until every validated point holds or max_cells are spent. A partial map is
    accepted (its non-ok cells are measured again first). The job's result names the refined map."""
    body = body or RefineRequest()
    job_id = service.submit_refinement(map_id, body, bench=body.bench)
    return job_public(service.records, service.records.get_job(job_id), service)


@router.get("/maps/{map_id}/validation", response_model=ValidationPublic, responses=error_responses(404))
def get_validation(map_id: ResourceId, service: ServiceDep) -> ValidationPublic:
    """The map's latest validation with every cell."""
    if service.records.get_map(map_id) is None:
        raise HTTPException(status.HTTP_404_NOT_FOUND, f"map {map_id} does not exist")
    row = service.records.latest_validation(map_id)
    if row is None:
        raise HTTPException(
            status.HTTP_404_NOT_FOUND, f"map {map_id} has not been validated: POST /maps/{map_id}/validate"
        )
    return validation_public(row)


def _map_dict(service, map_id: int, smooth: bool = False) -> dict:
    """The map as the exporters read it (its Public shape, as a dict)."""
    m = map_public(service.records, map_id, smooth=smooth)
    if m is None:
        raise HTTPException(status.HTTP_404_NOT_FOUND, f"map {map_id} does not exist")
    return m.model_dump()
