"""A map refined on the drive (a sweep of kind refinement): its rounds and its latest validation."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any, Mapping

from pydantic import BaseModel, Field

from service.api.public.validations import ValidationSummaryPublic, validation_summary_public

if TYPE_CHECKING:
    from service.calibration_service import Records


class RefinementRoundPublic(BaseModel):
    round: int = Field(description="0: the source map (its non-ok cells measured again first); k: after k insertions")
    map_id: int = Field(description="the map validated in this round")
    validation_id: int | None = None
    points: int = Field(description="validation points (grid points and midpoints)")
    below_target: int = Field(description="points below the target (or not measured)")
    grid_median_db: float | None = None
    midpoint_median_db: float | None = None
    min_db: float | None = None
    inserted: dict[str, list[float]] = Field(default_factory=dict, description="axis values inserted after it")
    remeasured: int = Field(0, description="cells identified again after it (their LUT entry missed at the cell)")
    new_cells: int = Field(0, description="cells the inserted values added")
    bytes: int | None = Field(None, description="the LUT image of this round's map, bytes of firmware memory")
    cells: int | None = Field(None, description="cells of this round's map")
    plant_time_s: float | None = Field(
        None,
        description="bench time of the round: its cells' settling and measurements and this validation, plant seconds",
    )
    point_s: float | None = Field(
        None,
        description="what a stepped validation point cost in this round's validation (settling and windows), plant "
        "seconds: the bench time budget's prediction of the next validation (null: every point was taken as it was)",
    )
    points_judged: int | None = Field(None, description="points judged (grid, midpoints, run-up bins)")
    held: int | None = Field(None, description="of them, how many hold")
    median_db: float | None = None
    harmful: int | None = Field(
        None, description="points where the LUT makes the order worse than no compensation (runup_validation.is_harm)"
    )
    injection_off: int | None = Field(None, description="cells the guard had turned injection off at (LUT flag 3)")
    no_injection: int | None = Field(
        None, description="judged points where the drive injects nothing (those cells weigh there): never harm"
    )


class PlacementRoundPublic(BaseModel):
    """A round of placement from theta* curves (service/maps/placement.py): candidates identified, kept where the
    drive's interpolation of their neighbours misses."""

    round: int
    candidates: dict[str, int] = Field(description="candidate values per axis, each a line of cells identified")
    inserted: dict[str, list[float]] = Field(description="the candidates kept, per axis")
    worst_predicted_db: dict[str, float | None] = Field(
        description="per axis, the worst LUT-mode suppression the candidates' lines predict without them, dB"
    )
    bytes: int = Field(description="the LUT image with what is kept so far, bytes")
    cells: int = Field(description="cells of the map with what is kept so far")
    plant_time_s: float = Field(
        description="bench time of the round's identifications (settling included), plant seconds"
    )
    left_out: list[str] = Field(default_factory=list, description="candidates that missed but did not fit max_bytes")


class RefinementPublic(BaseModel):
    """A map refined on the drive until its LUT holds (service/runs/refinement.py)."""

    refinement_id: int = Field(description="its sweep (kind refinement): pause, resume, cancel there")
    source_map_id: int
    map_id: int = Field(description="the refined map (the latest round's)")
    state: str
    phase: str = Field(description="measure | place | validate | guard | done")
    target_db: float
    max_cells: int
    max_bytes: int | None = Field(None, description="the LUT image budget, bytes")
    max_bench_s: float | None = Field(None, description="the bench time budget, plant seconds")
    bytes: int | None = Field(None, description="the LUT image of map_id, bytes")
    plant_time_s: float | None = Field(None, description="bench time spent in all rounds, plant seconds")
    cells_added: int = Field(description="cells identified by the refinement (new and re-measured)")
    holds: bool = Field(description="every point of the latest validation reached target_db")
    stopped: str | None = Field(None, description="why it ended before every point held (budget, rounds), one line")
    stopped_details: list[str] = Field(
        default_factory=list, description="each insertion the last round's plan left out, and why (one line each)"
    )
    placement: list[PlacementRoundPublic] = Field(
        default_factory=list, description="the placement rounds from curves, before the first validation"
    )
    rounds: list[RefinementRoundPublic]
    validation: ValidationSummaryPublic | None = Field(None, description="the latest validation of map_id")


def refinement_public(records: Records, sweep: Mapping[str, Any]) -> RefinementPublic:
    state = sweep["refinement"]
    latest = records.latest_validation(state["current_map_id"])
    rounds = [RefinementRoundPublic(**r) for r in state["rounds"]]
    holds = bool(rounds) and rounds[-1].below_target == 0 and rounds[-1].map_id == state["current_map_id"]
    return RefinementPublic(
        refinement_id=sweep["id"],
        source_map_id=sweep["source_map_id"],
        map_id=state["current_map_id"],
        state=sweep["state"],
        phase=state["phase"],
        target_db=state["target_db"],
        max_cells=state["max_cells"],
        max_bytes=state.get("max_bytes"),
        max_bench_s=state.get("max_bench_s"),
        bytes=rounds[-1].bytes if rounds else None,
        plant_time_s=state.get("plant_time_s"),
        cells_added=state["cells_added"],
        holds=holds,
        stopped=state.get("stopped"),
        stopped_details=state.get("stopped_details", []),
        placement=[PlacementRoundPublic(**r) for r in state.get("placement_rounds", [])],
        rounds=rounds,
        validation=validation_summary_public(latest) if latest else None,
    )
