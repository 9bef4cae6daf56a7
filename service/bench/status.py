"""The bench's status view: what /bench/status shows and the status poller reads.

Each device is read on its own (one failing device does not hide the others), never under the run
lock: each device's link has a lock of its own (the interlock monitor reads the same way), so the
view stays live while a run holds the bench. Every reading is kept with its time (`LiveValues`):
the view shows each value's age and marks it stale past STALE_AFTER_S.
"""

from __future__ import annotations

from datetime import datetime, timezone
from typing import Any, Callable, TypeVar

from drivers.drive import LutInForce
from drivers.lut_image import crc_hex
from service.bench.connections import BenchLinks
from service.bench.faults import BenchFaults
from service.bench.interlocks import daq_disconnected_reason
from service.bench.live_values import STALE_AFTER_S, LiveValues
from service.settings import Settings

Reading = TypeVar("Reading")


class BenchStatus:
    """The status view over the links and the interlocks (module doc); `busy()` says whether a run
    holds the bench."""

    def __init__(
        self, settings: Settings, identity: str, links: BenchLinks, faults: BenchFaults, busy: Callable[[], bool]
    ):
        self.settings = settings
        self.links = links
        self.faults = faults
        self._busy = busy
        self.live = LiveValues()  # every reading with its time (poller, the run's session, commands)
        # link state, last error; "lut" is the drive's LUT objects (0x2001), read apart from its status
        self._devices: dict[str, dict[str, Any]] = {"drive": {}, "load": {}, "supply": {}, "lut": {}}
        self._status: dict[str, Any] = {
            "connected": False,
            "bench": identity,
            "busy": False,
            "drive": None,
            "load": None,
            "daq": None,
            "supply": None,
            "lut": None,
            "updated_at": None,
            "error": None,
        }

    def refresh(self) -> dict[str, Any]:
        """Read drive/load/supply by SDO/SCPI, each on its own, never under the run lock (module doc),
        so a fault reset or a LUT download on an idle bench never waits for the poller (they take the
        run lock). The LUT the drive holds changes only by a download (which publishes it), so its
        objects are read when no run holds the bench, and not while the drive does not answer (its
        status read says so, without three more timeouts)."""
        if self.faults.connected:
            self.read_devices()
            if not self._busy() and self._devices["drive"].get("last_error") is None:
                self.read_lut(self.links.opened().drive.lut_in_force)
        self._status["updated_at"] = datetime.now(timezone.utc).isoformat(timespec="seconds")
        return self.status()

    def read_devices(self) -> None:
        links = self.links.opened()
        self._read_device(
            "drive",
            lambda: links.drive.read_status(),
            lambda d: {"state": d.state.value, "torque_nm": d.torque_nm, "speed_rpm": d.speed_rpm, "udc_v": d.udc_v},
        )
        self._read_device(
            "load", lambda: links.load.read_status(), lambda l: {"state": l.state.value, "speed_rpm": l.speed_rpm}
        )
        self._read_device("supply", lambda: links.supply.measure_voltage(), lambda v: {"measured_v": v})

    def read_lut(self, read: Callable[[], LutInForce]) -> None:
        """The LUT the drive holds, as `read()` returns it (its objects, or a download's read-back)."""
        self._read_device("lut", read, _lut_shape)

    def _read_device(self, name: str, read: Callable[[], Reading], shape: Callable[[Reading], dict[str, Any]]) -> None:
        entry = self._devices[name]
        try:
            self.live.publish(name, **shape(read()))
            entry["last_error"] = None
        except Exception as exc:  # status must never take the service down
            entry["last_error"] = f"{type(exc).__name__}: {exc}"

    def mark_closed(self) -> None:
        self._status["connected"] = False

    def status(self) -> dict[str, Any]:
        """The truth per device: live link state (heartbeats, DAQ port) plus the last readings, each
        with its age (`ages`, s) and `stale` past STALE_AFTER_S; `run`: what the run in flight sees on
        the DAQ (encoder speed, the h-th acceleration amplitude); `error` is the first thing wrong."""
        s, links = self.settings, self.links
        busy = self._busy()
        common = {
            "busy": busy,
            "stale_after_s": STALE_AFTER_S,
            "accel_full_scale_rad_s2": s.daq.accel_full_scale_rad_s2,
        }
        if not self.faults.connected:
            u = links.unreachable
            return {
                **self._status,
                **common,
                "connected": False,
                "unreachable": u,
                "error": links.unreachable_trip().reason if u else self._status.get("error"),
            }
        opened = links.opened()
        out = {**self._status, **common, "connected": opened.bus.connected, "unreachable": None}

        def device(name: str, live: dict[str, Any]) -> dict[str, Any]:
            values, ages = self.live.group(name)
            oldest = max(ages.values()) if ages else None
            return {
                **values,
                **self._devices[name],
                **live,
                "ages": ages,
                "age_s": oldest,
                "stale": oldest is None or oldest > STALE_AFTER_S,
            }

        for name, dev in (("drive", opened.drive), ("load", opened.load)):
            age = dev.heartbeat_age_s()
            out[name] = device(
                name,
                {
                    "connected": dev.heartbeat_alive(),
                    "heartbeat_ok": dev.heartbeat_alive(),
                    "heartbeat_age_s": None if age is None else round(age, 2),
                },
            )
        out["supply"] = device("supply", {"url": s.supply.url})
        out["supply"]["connected"] = out["supply"].get("last_error") is None and out["supply"]["age_s"] is not None
        out["lut"] = device("lut", {})  # read when idle and at each download: its age says when
        c = opened.daq.counters
        out["daq"] = {
            **opened.daq.health(),
            "frames": c.frames,
            "crc_failures": c.crc_failures,
            "sequence_gaps": c.sequence_gaps,
        }
        run, run_ages = self.live.group("run")
        if run.get("harmonic_amplitude_fs") is not None:
            run["harmonic_amplitude_rad_s2"] = run["harmonic_amplitude_fs"] * s.daq.accel_full_scale_rad_s2
            run_ages["harmonic_amplitude_rad_s2"] = run_ages["harmonic_amplitude_fs"]
        out["run"] = {**run, "active": busy, "ages": run_ages}
        out["service_heartbeat_ok"] = opened.bus.heartbeat_producing()
        out["interlocks"] = self.faults.started().monitor.snapshot()
        problems = [t["reason"] for t in out["interlocks"]["tripped"]]
        if not out["daq"]["connected"] and not any(p.startswith("DAQ") for p in problems):
            # the link is known lost before the interlock's next round names it
            problems.append(daq_disconnected_reason(out["daq"]["url"], out["daq"]["last_error"]))
        problems += [f"{n}: {out[n]['last_error']}" for n in ("drive", "load", "supply") if out[n].get("last_error")]
        out["error"] = problems[0] if problems else None
        return out


def _lut_shape(held: LutInForce) -> dict[str, Any]:
    """The LUT the drive holds as /bench/status shows it: no map id and no CRC while it holds none."""
    return {"map_id": held.map_id or None, "crc32": crc_hex(held.crc32) if held.map_id else None, "status": held.status}
