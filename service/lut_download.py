"""A map into the drive's LUT (0x2001): what may go, the download, and the receipt.

Only `ok` cells are valid in a LUT (DESIGN 6): the drive injects nothing at the others. A map
without one ok cell is refused; a partial map goes only when asked with `force`, so a LUT with holes
is never loaded by mistake. The image (drivers/lut_image.py) carries the map id; the drive reports
map id and CRC back, and /bench/status shows them. Used by POST /maps/{id}/download, the CLI's
`maps download` and the validation job (which calls `download_map`).
"""
from __future__ import annotations

from dataclasses import dataclass

from drivers.lut_image import crc_hex
from service.bench import Bench, BenchError
from service.lut_export import lut_image
from service.public import LutDownloadPublic, map_public
from service.storage import Storage


class MapNotFound(LookupError):
    pass


class LutRefused(ValueError):
    """The map cannot go into the drive at all (no ok cell, or it cannot become an image)."""


class PartialMap(ValueError):
    """Some cells are not ok: the map goes only with force."""

    def __init__(self, map_id: int, not_ok: int, cells: int, how_to_force: str):
        self.what = f"map {map_id} is partial: {not_ok} of {cells} cells are not ok and would inject nothing"
        super().__init__(f"{self.what}; {how_to_force}")


@dataclass(frozen=True)
class PreparedLut:
    """A map checked and encoded, before anything goes to the bench."""
    map_id: int
    image: bytes
    cells: int
    valid_cells: int
    harmonic_order: int
    forced: bool


def prepare(storage: Storage, map_id: int, force: bool = False) -> PreparedLut:
    """Check the download rules and build the image. Raises MapNotFound, LutRefused, PartialMap."""
    m = map_public(storage, map_id)
    if m is None:
        raise MapNotFound(f"map {map_id} does not exist")
    cells = len(m.cells)
    valid = sum(1 for c in m.cells if c.status == "ok")
    if valid == 0:
        raise LutRefused(f"map {map_id} has no valid cell (0 of {cells} ok): a LUT without one would inject "
                         f"nothing; measure the sweep again")
    if valid < cells and not force:
        raise PartialMap(map_id, cells - valid, cells, "load it anyway with force (API: ?force=true, CLI: --force)")
    try:
        image = lut_image(m.model_dump())
    except ValueError as exc:
        raise LutRefused(f"map {map_id} cannot become a LUT: {exc}") from None
    return PreparedLut(map_id, image, cells, valid, m.harmonic_order, forced=valid < cells)


def send(bench: Bench, lut: PreparedLut) -> LutDownloadPublic:
    """The image into the drive, CRC and map id read back. Raises BenchError (busy, not reached, the
    drive reports another map) or the driver's SDO errors (the drive refused or did not answer)."""
    held = bench.download_lut(lut.image)
    if held.map_id != lut.map_id:
        raise BenchError(f"the drive reports map {held.map_id} in force after map {lut.map_id} was downloaded "
                         f"(CRC {crc_hex(held.crc32)}, status {held.status})")
    return LutDownloadPublic(map_id=lut.map_id, crc32=crc_hex(held.crc32), bytes=len(lut.image), cells=lut.cells,
                             valid_cells=lut.valid_cells, harmonic_order=lut.harmonic_order, forced=lut.forced)


def download_map(storage: Storage, bench: Bench, map_id: int, force: bool = False) -> LutDownloadPublic:
    """Map `map_id` into the drive under the rules above; the receipt says what went in."""
    return send(bench, prepare(storage, map_id, force))
