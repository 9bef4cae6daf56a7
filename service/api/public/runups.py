"""A run-up's order analysis as answered (DESIGN section 6: the result of a job of kind `runup`)."""

from __future__ import annotations

from typing import Any, Mapping

from pydantic import BaseModel, Field


class ProminentOrderPublic(BaseModel):
    """An order above the noise over the range (service/model/order_tracking.py prominent_orders)."""

    order: int
    max_amplitude: float = Field(description="the largest bin amplitude over the range, sensor full scale")
    at_speed_rpm: float = Field(description="the bin of that largest amplitude")
    median_above_floor_db: float = Field(description="median over the fitted bins of the order over the floor, dB")
    fraction_above: float = Field(description="of the fitted bins, the fraction at least list_above_db above")


class RunupPublic(BaseModel):
    """Each tracked order's amplitude and phase per speed bin of a speed ramp at constant torque
    (service/runs/runup.py, service/model/order_tracking.py). null where an order was not fitted in a bin."""

    state: str = Field(description="done | failed | cancelled")
    error: str | None = None
    speed_rpm: list[float] = Field(default_factory=list, description="bin centres, <= 10 rpm apart")
    orders: list[int] = Field(default_factory=list, description="electrical orders tracked")
    amplitude: list[list[float | None]] = Field(
        default_factory=list, description="[order][bin], sensor full scale: |complex mean of the bin's windows|"
    )
    phase_deg: list[list[float | None]] = Field(default_factory=list, description="[order][bin], (-180, 180] deg")
    noise_floor: list[float | None] = Field(
        default_factory=list, description="[bin], fs: the rms amplitude an order without a tone shows in the bin"
    )
    windows: list[int] = Field(default_factory=list, description="[bin]: whole-period windows averaged")
    orders_above: list[ProminentOrderPublic] = Field(
        default_factory=list,
        description="the orders to pick for compensation, largest first: at least list_above_db above the bin's "
        "noise floor in at least a quarter of the bins where they were fitted",
    )
    list_above_db: float | None = None
    bin_rpm: float | None = None
    harmonic_order: int | None = None
    torque_nm: float | None = None
    torque_actual_nm: float | None = Field(None, description="mean of the drive's 0x6077 over the run-up")
    udc_v: float | None = None
    direction: str | None = None
    injection: str | None = None
    rate_rpm_per_s: float | None = None
    plant_time_s: float | None = Field(None, description="settling at the first speed and the ramps, plant s")
    ramp_plant_s: float | None = None
    samples: int | None = None
    bench_identity: str
    software_version: str
    started_at: str
    finished_at: str


def runup_public(row: Mapping[str, Any]) -> RunupPublic:
    return RunupPublic(
        state=row["state"],
        error=row.get("error"),
        bench_identity=row["bench_identity"],
        software_version=row["software_version"],
        started_at=row["started_at"],
        finished_at=row["finished_at"],
        **(row.get("result") or {}),
    )
