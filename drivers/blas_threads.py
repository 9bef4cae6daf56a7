"""How many threads BLAS runs in this process: one, for the process's life.

Both processes call `one_blas_thread()` at start (the service, service/calibration_service.py, and the
emulated bench, plant_emulator/process.py), so it lives apart from the CAN bus it protects: importing it
drags nothing else in.
"""

from __future__ import annotations

from threadpoolctl import threadpool_limits


def one_blas_thread() -> None:
    """Run BLAS on one thread in this process, for good (call once at process start; both the
    service and the emulated devices do). OpenBLAS workers spin while they wait for work: on a
    loaded 2-core PC they kept the heartbeat thread off the CPU for over a second and the drive fell
    safe (EMCY 0x8130). Our least-squares problems have tens of columns: one thread is as fast."""
    threadpool_limits(limits=1)
