"""A result (one identification at one operating point) and its raw recording, from the result's row
(service/store/result_rows.py makes the row)."""

from __future__ import annotations

from typing import Any, Mapping

from pydantic import BaseModel, Field

from service.maps.compare import ComplexGain
from service.model.operating_point import OperatingPoint
from service.store.recordings import recording_record, unavailable_reason


class PhasorPublic(BaseModel):
    a_c: float = Field(description="(2/N) sum(alpha cos(h phi_e)), sensor full scale")
    a_s: float = Field(description="(2/N) sum(alpha sin(h phi_e)), sensor full scale")
    amplitude: float


class RecordingPublic(BaseModel):
    """The raw recording of one identification (DAQ samples and theta setpoints, MF4)."""

    available: bool = Field(description="the file can be downloaded (url)")
    format: str = Field("mf4", description="mf4: ASAM MDF 4.10")
    url: str | None = Field(None, description="GET it here while available")
    bytes: int | None = None
    samples: int | None = Field(
        None,
        description="DAQ samples in the file: those counted in plant_time_s "
        "(samples = plant_time_s x sample_rate_hz when the DAQ lost none)",
    )
    stale_samples: int | None = Field(
        None, description="samples read before a setpoint took effect: counted, not in the file"
    )
    setpoints: int | None = Field(None, description="theta setpoints, each with the sample at which it took effect")
    sample_rate_hz: float | None = None
    error: str | None = Field(
        None, description="why it is not available: the write failed (and why), or retention deleted it"
    )


class OrderResultPublic(BaseModel):
    """One order of a result with several (DESIGN section 6): judged on its own against its own target."""

    order: int
    status: str = Field(description="ok (met target_db) | below_target | no_authority | failed")
    theta_cos: float = Field(description="rad")
    theta_sin: float = Field(description="rad")
    gamma_deg: float
    delta_deg: float
    suppression_db: float
    target_db: float
    noise_floor_db: float | None = Field(
        None, description="the final window's noise against this order's uncompensated amplitude, dB"
    )
    reason: str


class ResultPublic(BaseModel):
    """One identification at one operating point, self-describing (statuses: docs/conventions.md, Statuses)."""

    id: int
    status: str = Field(description="ok (met target_db) | below_target | no_authority | failed")
    error: str | None = Field(None, description="for every status but ok: the reason a test engineer can act on")
    message: str | None = None
    method: str
    operating_point: OperatingPoint
    harmonic_order: int
    gamma_deg: float | None = None
    delta_deg: float | None = None
    theta_cos: float | None = Field(None, description="rad")
    theta_sin: float | None = Field(None, description="rad")
    residual: PhasorPublic | None = None
    uncompensated: PhasorPublic | None = None
    suppression_db: float | None = None
    target_db: float | None = None
    noise_floor_db: float | None = Field(
        None, description="rms noise phasor of the final window against |uncompensated|"
    )
    torque_actual_nm: float | None = Field(
        None,
        description="the torque the point ran at: the drive's torque actual, mean over the measurement, Nm "
        "(a result whose torque left its command beyond safety.torque_tolerance_* is never ok)",
    )
    plant_time_s: float | None = Field(None, description="DAQ samples / rate, counted from each setpoint's effect")
    windows_used: int | None = None
    windows_discarded: int | None = None
    s_model: ComplexGain | None = None
    s_measured: ComplexGain | None = None
    orders: list[OrderResultPublic] | None = Field(
        None,
        description="several orders cancelled jointly (method probe-orders): every order's own result, the "
        "first the run's harmonic order (whose fields the result's own are); null for one order",
    )
    details: dict[str, Any] | None = None
    options: dict[str, Any]
    bench_identity: str
    software_version: str
    started_at: str
    finished_at: str
    traces: dict[str, Any] = Field(default_factory=dict, description="data to redraw the result's plots")
    recording: RecordingPublic | None = Field(None, description="its raw recording (null: none was attempted)")


def result_public(row: Mapping[str, Any], with_traces: bool = True) -> ResultPublic:
    """The API view of a stored result row (traces left out where a list shows many results)."""
    detail = row.get("detail") or {}
    return ResultPublic(
        id=row["id"],
        status=row["status"],
        error=row["error"],
        method=row["method"],
        message=detail.get("message"),
        operating_point=OperatingPoint(torque_nm=row["torque_nm"], speed_rpm=row["speed_rpm"], udc_v=row["udc_v"]),
        harmonic_order=row["harmonic_order"],
        gamma_deg=row.get("gamma_deg"),
        delta_deg=row.get("delta_deg"),
        theta_cos=row.get("theta_cos"),
        theta_sin=row.get("theta_sin"),
        residual=detail.get("residual"),
        uncompensated=detail.get("uncompensated"),
        suppression_db=row.get("suppression_db"),
        target_db=row.get("target_db"),
        noise_floor_db=row.get("noise_floor_db"),
        torque_actual_nm=row.get("torque_actual_nm"),
        plant_time_s=row.get("plant_time_s"),
        windows_used=row.get("windows_used"),
        windows_discarded=detail.get("windows_discarded"),
        s_model=detail.get("s_model"),
        s_measured=detail.get("s_measured"),
        orders=_orders(detail.get("details")),
        details=detail.get("details"),
        options=row["options"],
        bench_identity=row["bench_identity"],
        software_version=row["software_version"],
        started_at=row["started_at"],
        finished_at=row["finished_at"],
        traces=(row.get("traces") or {}) if with_traces else {},
        recording=_recording(row),
    )


def _recording(row: Mapping[str, Any]) -> RecordingPublic | None:
    record = recording_record(row)
    if record is None:
        return None
    why = unavailable_reason(record)
    fmt = record.get("format", "mf4")
    return RecordingPublic(
        available=why is None,
        format=fmt,
        error=why,
        url=f"/api/v1/results/{row['id']}/recording?format={fmt}" if why is None else None,
        **{k: record.get(k) for k in ("bytes", "samples", "stale_samples", "setpoints", "sample_rate_hz")},
    )


def _orders(details: Mapping[str, Any] | None) -> list[OrderResultPublic] | None:
    orders = (details or {}).get("orders")
    if not orders:
        return None
    return [
        OrderResultPublic.model_validate({k: o[k] for k in OrderResultPublic.model_fields if k in o}) for o in orders
    ]
