"""A map into the drive's LUT (0x2001): what may go, the download, and the receipt.

The drive injects at the LUT's entries: `ok` cells (flag 1) and, when the download takes the fill
(`fill`, default True), the filled cells (flag 2: a cell not ok that carries a fill, service/maps/fill.py).
A cell with injection off (flag 3, set on the stored map) is a choice, not a hole: the drive injects
nothing in any interval with it as a corner. Every other cell is a hole: the drive injects nothing there. A map without one ok cell is refused
(whatever its fills: no cell met its target); a map with holes under the chosen fill goes only when
asked with `force`, so a LUT with holes is never loaded by mistake. The interpolation mode goes into
the image's header (None: lut_export.DEFAULT_INTERPOLATION). The image (service/maps/lut_export.py,
encoded by drivers/lut_image.py: the runs floor sees the LUT image through maps only) carries the map
id; the drive reports map id and CRC back, and /bench/status shows them. Used by
POST /maps/{id}/download, the CLI's `maps download` and the validation job (which calls `download_map`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from pydantic import BaseModel, Field

from service.bench.bench import Bench, BenchError
from service.errors import Conflict, Invalid, NotFound
from service.maps.lut_export import DEFAULT_INTERPOLATION, LUT_FORMAT_VERSION, crc_hex, lut_entries, lut_image
from service.maps.view import map_view
from service.store.storage import Storage


class LutDownload(BaseModel):
    """What went into the drive (POST /maps/{id}/download, `ripplecal maps download`, a validation job)."""

    map_id: int = Field(description="the map the drive now holds (it reports it on 0x2001:4)")
    crc32: str = Field(
        description="CRC-32 (zlib) of the LUT image without its CRC field, as the drive read it "
        "back (0x2001:2): 0x and 8 hex digits"
    )
    bytes: int = Field(description="size of the LUT image")
    cells: int = Field(description="cells of the map")
    valid_cells: int = Field(description="cells with status ok (VALID)")
    filled_cells: int = Field(
        0,
        description="cells not ok that went in with their fill (service/maps/fill.py); "
        "the drive injects at ok and filled cells",
    )
    injection_off_cells: int = Field(
        0,
        description="cells that went in with injection off (LUT flag 3): the drive injects nothing in "
        "any interval with one as a corner",
    )
    fill: bool = Field(True, description="whether the fills were chosen for this download")
    interpolation: str = Field(
        "cartesian",
        description="what the drive interpolates between cells: cartesian "
        "(theta_cos, theta_sin) or polar (gamma, delta along the shortest arc)",
    )
    format_version: int = Field(3, description="LUT image format version (drivers/lut_image.py)")
    harmonic_order: int
    orders: list[int] = Field(
        default_factory=list,
        description="every order the drive now injects in LUT mode, the map's own first ([6] for a map of one)",
    )
    forced: bool = Field(description="true when a map with holes (cells that inject nothing) went in on force=true")


class MapNotFound(NotFound):
    pass


class LutRefused(Invalid, ValueError):
    """The map cannot go into the drive at all (no ok cell, or it cannot become an image)."""


class PartialMap(Conflict, ValueError):
    """Some cells would inject nothing under the chosen fill: the map goes only with force."""

    def __init__(
        self, map_id: int, holes: int, cells: int, how_to_force: str, fill: bool = True, filled_left_out: int = 0
    ):
        if fill:
            which = " and carry no fill"
        elif filled_left_out:
            which = f" ({filled_left_out} of them filled, left out without fill)"
        else:
            which = ""
        self.what = (
            f"map {map_id} is partial: {holes} of {cells} cells are not ok{which}: the drive would inject nothing there"
        )
        super().__init__(f"{self.what}; {how_to_force}")


@dataclass(frozen=True)
class PreparedLut:
    """A map checked and encoded, before anything goes to the bench."""

    map_id: int
    image: bytes
    cells: int
    valid_cells: int  # ok cells (flag 1)
    harmonic_order: int
    forced: bool  # holes under the chosen fill, loaded on force
    filled_cells: int = 0  # filled cells in the image (flag 2); 0 without fill
    fill: bool = True
    interpolation: str = DEFAULT_INTERPOLATION
    format_version: int = LUT_FORMAT_VERSION
    injection_off_cells: int = 0  # cells with injection off (flag 3), chosen: never holes
    orders: tuple[int, ...] = ()  # a map of several orders: all of them, its own first

    @property
    def holes(self) -> int:
        """Cells without an entry and not chosen off: the drive injects nothing there."""
        return self.cells - self.valid_cells - self.filled_cells - self.injection_off_cells

    def receipt_fields(self) -> dict[str, Any]:
        """What the receipt says went in beyond LutDownload's first fields."""
        return {
            "filled_cells": self.filled_cells,
            "injection_off_cells": self.injection_off_cells,
            "fill": self.fill,
            "interpolation": self.interpolation,
            "format_version": self.format_version,
            "orders": list(self.orders) or [self.harmonic_order],
        }


def prepare(
    storage: Storage, map_id: int, force: bool = False, fill: bool = True, interpolation: str | None = None
) -> PreparedLut:
    """Check the download rules and build the image. Raises MapNotFound, LutRefused, PartialMap."""
    m = map_view(storage, map_id)
    if m is None:
        raise MapNotFound(f"map {map_id} does not exist")
    view = m.model_dump()
    try:
        entries = lut_entries(view, fill, interpolation)
    except ValueError as exc:
        raise LutRefused(str(exc)) from None
    valid, filled, holes, cells = entries.ok, entries.filled, entries.holes, entries.cells
    if valid == 0:
        raise LutRefused(
            f"map {map_id} has no valid cell (0 of {cells} ok): a LUT without one would inject "
            f"nothing at a measured target; measure the sweep again"
        )
    if holes and not force:
        raise PartialMap(
            map_id,
            holes,
            cells,
            "load it anyway with force (API: ?force=true, CLI: --force)",
            fill,
            entries.fills_left_out,
        )
    try:
        image = lut_image(view, fill=fill, interpolation=entries.interpolation)
    except ValueError as exc:
        raise LutRefused(f"map {map_id} cannot become a LUT: {exc}") from None
    return PreparedLut(
        map_id,
        image,
        cells,
        valid,
        m.harmonic_order,
        forced=holes > 0,
        filled_cells=filled,
        fill=fill,
        interpolation=entries.interpolation,
        format_version=entries.format_version,
        injection_off_cells=entries.injection_off,
        orders=entries.orders,
    )


def send(bench: Bench, lut: PreparedLut) -> LutDownload:
    """The image into the drive, CRC and map id read back. Raises BenchError (busy, not reached, the
    drive reports another map) or the driver's SDO errors (the drive refused or did not answer)."""
    held = bench.download_lut(lut.image)
    if held.map_id != lut.map_id:
        raise BenchError(
            f"the drive reports map {held.map_id} in force after map {lut.map_id} was downloaded "
            f"(CRC {crc_hex(held.crc32)}, status {held.status})"
        )
    # the receipt's newer fields (filled_cells, fill, interpolation, format_version) where the model has them
    extra = {k: v for k, v in lut.receipt_fields().items() if k in LutDownload.model_fields}
    return LutDownload(
        map_id=lut.map_id,
        crc32=crc_hex(held.crc32),
        bytes=len(lut.image),
        cells=lut.cells,
        valid_cells=lut.valid_cells,
        harmonic_order=lut.harmonic_order,
        forced=lut.forced,
        **extra,
    )


def download_map(
    storage: Storage,
    bench: Bench,
    map_id: int,
    force: bool = False,
    fill: bool = True,
    interpolation: str | None = None,
) -> LutDownload:
    """Map `map_id` into the drive under the rules above; the receipt says what went in."""
    return send(bench, prepare(storage, map_id, force, fill, interpolation))
