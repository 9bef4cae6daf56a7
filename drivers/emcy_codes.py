"""Meanings of EMCY error codes (CiA 301 communication, CiA 402 / IEC 61800-7-201 drive profile).

An operator reads "EMCY 0x3210 DC link over-voltage", not "0x3210": the interlock reasons, job
errors and sweep pause reasons name the code with its meaning. Exact codes first, then the code's
class (high byte, then high nibble) so that an unlisted vendor code still says what area it is in.
"""

from __future__ import annotations

EXACT: dict[int, str] = {
    0x0000: "error reset / no error",
    0x1000: "generic error",
    0x2110: "short circuit/earth leakage (input)",
    0x2210: "continuous over-current (inside the device)",
    0x2220: "short circuit/earth leakage (inside the device)",
    0x2310: "continuous over-current (device output side)",
    0x2311: "continuous over-current no. 1",
    0x2312: "continuous over-current no. 2",
    0x2320: "short circuit/earth leakage (device output side)",
    0x2330: "earth leakage (device output side)",
    0x2340: "short circuit (device output side)",
    0x3110: "mains over-voltage",
    0x3120: "mains under-voltage",
    0x3130: "phase failure",
    0x3210: "DC link over-voltage",
    0x3220: "DC link under-voltage",
    0x3230: "load error",
    0x3310: "output over-voltage",
    0x4110: "excess ambient temperature",
    0x4210: "excess temperature device",
    0x4310: "excess temperature drive",
    0x5112: "supply low voltage (U2 = +24 V)",
    0x5113: "supply low voltage (U3 = +5 V)",
    0x5210: "measurement circuit fault",
    0x5530: "data storage (non-volatile memory) fault",
    0x6010: "software reset (watchdog)",
    0x6320: "parameter error",
    0x7110: "brake chopper failure",
    0x7120: "motor error",
    0x7121: "motor blocked",
    0x7305: "incremental sensor 1 fault",
    0x7310: "speed sensor fault",
    0x7320: "position sensor fault",
    0x8110: "CAN overrun (objects lost)",
    0x8120: "CAN in error passive mode",
    0x8130: "heartbeat lost (life guard or heartbeat error)",
    0x8140: "recovered from bus off",
    0x8210: "PDO not processed due to length error",
    0x8311: "excess torque",
    0x8611: "following error",
    0x9000: "external error",
    0xFF00: "device specific",
}

CLASSES: dict[int, str] = {
    0x10: "generic error",
    0x20: "current",
    0x21: "current, device input side",
    0x22: "current inside the device",
    0x23: "current, device output side",
    0x30: "voltage",
    0x31: "mains voltage",
    0x32: "voltage inside the device",
    0x33: "output voltage",
    0x40: "temperature",
    0x41: "ambient temperature",
    0x42: "device temperature",
    0x43: "drive temperature",
    0x50: "device hardware",
    0x60: "device software",
    0x70: "additional modules",
    0x80: "monitoring",
    0x81: "communication",
    0x82: "protocol error",
    0x83: "torque control",
    0x86: "position control",
    0x90: "external error",
    0xF0: "additional functions",
    0xFF: "device specific",
}


def emcy_meaning(code: int) -> str:
    """'DC link over-voltage' for 0x3210; the class for codes not listed; never raises."""
    if code in EXACT:
        return EXACT[code]
    hi = (code >> 8) & 0xFF
    if hi in CLASSES:
        return f"{CLASSES[hi]} (code not listed)"
    if (hi & 0xF0) in CLASSES:
        return f"{CLASSES[hi & 0xF0]} (code not listed)"
    return "unknown error code"


def describe_emcy(code: int) -> str:
    """'EMCY 0x3210 DC link over-voltage'."""
    return f"EMCY 0x{code:04X} {emcy_meaning(code)}"
