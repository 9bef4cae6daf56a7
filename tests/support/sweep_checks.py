"""What a finished sweep's points must show, whatever the machine: every point measured (none lost to a
fault or a restart), each stored honestly (ok only at its target, every other status with its reason).
How many cells reach 40 dB is the sweep-quality benchmark's figure, not an end-to-end test's."""

from __future__ import annotations

import json

from service.store.storage import Storage

MEASURED = ("ok", "below_target", "no_authority")


def assert_points_measured_honestly(points: list[dict], min_ok: int) -> None:
    def brief(p: dict) -> str:
        r = p.get("result") or {}
        return (
            f"{p['operating_point']}: {p['state']} {r.get('suppression_db')} dB "
            f"(target {r.get('target_db')}): {p.get('error') or r.get('error')}"
        )

    unmeasured = [brief(p) for p in points if p["state"] not in MEASURED or p.get("result") is None]
    assert not unmeasured, "points not measured: " + "; ".join(unmeasured)
    dishonest = [
        brief(p)
        for p in points
        if (p["state"] == "ok") != (p["result"]["status"] == "ok")
        or p["state"] == "ok"
        and p["result"]["suppression_db"] < p["result"]["target_db"]
        or p["state"] != "ok"
        and not p["result"]["error"]
    ]
    assert not dishonest, "stored ok below target, or not ok without a reason: " + "; ".join(dishonest)
    ok = sum(p["state"] == "ok" for p in points)
    assert ok >= min_ok, f"{ok} of {len(points)} points ok (expected >= {min_ok}): " + "; ".join(
        brief(p) for p in points if p["state"] != "ok"
    )


def cells_not_ok(m: dict) -> int:
    """Cells of a map (as GET /maps/{id} answers) that are not ok (status_counts has no key for a status
    no cell has)."""
    return len(m["cells"]) - m["status_counts"].get("ok", 0)


def holes(m: dict) -> int:
    """Cells that would inject nothing in a download with the fill (the default): neither ok nor filled.
    A download refuses the map unless forced when there is one."""
    return sum(1 for c in m["cells"] if c["status"] != "ok" and not c.get("filled"))


def results_per_point(db, sweep_id: int, first_pass_only: bool = False) -> dict[tuple, int]:
    """Stored attempts per operating point of a sweep, read from the database itself (a SQLite file or a
    postgresql:// URL); `first_pass_only`: leave out the second pass, which measures a non-ok cell once
    more by design."""
    storage = Storage(db)
    try:
        with storage.connect() as conn:
            rows = conn.execute(
                "SELECT torque_nm, speed_rpm, udc_v, detail_json FROM results WHERE sweep_id = ?", (sweep_id,)
            ).fetchall()
    finally:
        storage.close()
    counts: dict[tuple, int] = {}
    for r in rows:
        if first_pass_only and (json.loads(r[3] or "{}").get("details") or {}).get("sweep_pass", 1) != 1:
            continue
        counts[(r[0], r[1], r[2])] = counts.get((r[0], r[1], r[2]), 0) + 1
    return counts
