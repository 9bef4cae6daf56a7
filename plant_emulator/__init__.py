"""Emulated test bench: PMSM + drive firmware + load machine + DC supply + DAQ behind real wires.

`python -m plant_emulator` starts one process speaking socketcand (CANopen), SCPI over TCP and the
DAQ frame protocol on a pty (docs/interfaces.md, "Emulator process"; its truth: docs/scenarios.md).
"""
