"""CiA 402 power drive state machine: one table, used by both sides of the wire.

The drive firmware in plant_emulator walks `DEVICE_TRANSITIONS`; the master in drivers/ decodes the
statusword with `decode_statusword` and follows `PATH_TO_OPERATION_ENABLED`. Bit patterns are those of
CiA 402 (IEC 61800-7-201), section "Statusword" and "Controlword", taken from canopen's own table
(`canopen.profiles.p402.State402`: SW_MASK and the CW_* words), so the master, the emulated devices and
the library agree on one definition; what is ours is the names, the device's transitions and the path.
"""

from __future__ import annotations

from enum import Enum

from canopen.profiles.p402 import State402 as _P402


class State402(str, Enum):
    NOT_READY_TO_SWITCH_ON = "not_ready_to_switch_on"
    SWITCH_ON_DISABLED = "switch_on_disabled"
    READY_TO_SWITCH_ON = "ready_to_switch_on"
    SWITCHED_ON = "switched_on"
    OPERATION_ENABLED = "operation_enabled"
    QUICK_STOP_ACTIVE = "quick_stop_active"
    FAULT_REACTION_ACTIVE = "fault_reaction_active"
    FAULT = "fault"


# statusword (mask, value) per state: canopen's table, keyed by our names ("SWITCH ON DISABLED" ->
# State402.SWITCH_ON_DISABLED); the patterns are disjoint, so their order does not matter
STATUSWORD_PATTERNS: dict[State402, tuple[int, int]] = {
    State402[name.replace(" ", "_")]: pattern for name, pattern in _P402.SW_MASK.items()
}

STATUSWORD_VOLTAGE_ENABLED = 1 << 4
STATUSWORD_REMOTE = 1 << 9
STATUSWORD_TARGET_REACHED = 1 << 10


class Command402(str, Enum):
    SHUTDOWN = "shutdown"
    SWITCH_ON = "switch_on"
    ENABLE_OPERATION = "enable_operation"
    DISABLE_VOLTAGE = "disable_voltage"
    QUICK_STOP = "quick_stop"
    DISABLE_OPERATION = "disable_operation"
    FAULT_RESET = "fault_reset"


# controlword value the master sends for each command (canopen's CW_* words; its CW_SWITCH_ON_DISABLED
# is the fault reset, transition 15, and 'disable operation' is coded as 'switch on')
CONTROLWORD: dict[Command402, int] = {
    Command402.SHUTDOWN: _P402.CW_SHUTDOWN,
    Command402.SWITCH_ON: _P402.CW_SWITCH_ON,
    Command402.ENABLE_OPERATION: _P402.CW_OPERATION_ENABLED,
    Command402.DISABLE_VOLTAGE: _P402.CW_DISABLE_VOLTAGE,
    Command402.QUICK_STOP: _P402.CW_QUICK_STOP,
    Command402.DISABLE_OPERATION: _P402.CW_SWITCH_ON,
    Command402.FAULT_RESET: _P402.CW_SWITCH_ON_DISABLED,
}

# (current state, command) -> next state; anything not in the table leaves the state unchanged
S, C = State402, Command402
DEVICE_TRANSITIONS: dict[tuple[State402, Command402], State402] = {
    (S.SWITCH_ON_DISABLED, C.SHUTDOWN): S.READY_TO_SWITCH_ON,  # 2
    (S.READY_TO_SWITCH_ON, C.SWITCH_ON): S.SWITCHED_ON,  # 3
    (S.READY_TO_SWITCH_ON, C.ENABLE_OPERATION): S.OPERATION_ENABLED,  # 3+4
    (S.SWITCHED_ON, C.ENABLE_OPERATION): S.OPERATION_ENABLED,  # 4
    # 5: 'disable operation' is coded 0x07, the same word as 'switch on'
    (S.OPERATION_ENABLED, C.SWITCH_ON): S.SWITCHED_ON,  # 5
    (S.SWITCHED_ON, C.SHUTDOWN): S.READY_TO_SWITCH_ON,  # 6
    (S.READY_TO_SWITCH_ON, C.DISABLE_VOLTAGE): S.SWITCH_ON_DISABLED,  # 7
    (S.READY_TO_SWITCH_ON, C.QUICK_STOP): S.SWITCH_ON_DISABLED,  # 7
    (S.OPERATION_ENABLED, C.SHUTDOWN): S.READY_TO_SWITCH_ON,  # 8
    (S.OPERATION_ENABLED, C.DISABLE_VOLTAGE): S.SWITCH_ON_DISABLED,  # 9
    (S.SWITCHED_ON, C.DISABLE_VOLTAGE): S.SWITCH_ON_DISABLED,  # 10
    (S.SWITCHED_ON, C.QUICK_STOP): S.SWITCH_ON_DISABLED,  # 10
    (S.OPERATION_ENABLED, C.QUICK_STOP): S.QUICK_STOP_ACTIVE,  # 11
    (S.QUICK_STOP_ACTIVE, C.DISABLE_VOLTAGE): S.SWITCH_ON_DISABLED,  # 12
    (S.FAULT, C.FAULT_RESET): S.SWITCH_ON_DISABLED,  # 15
}
del S, C

# states in which the power stage is on and torque may flow
TORQUE_STATES = frozenset({State402.OPERATION_ENABLED, State402.QUICK_STOP_ACTIVE})

# commands the master issues, from each state, on the way to OPERATION_ENABLED
PATH_TO_OPERATION_ENABLED: dict[State402, Command402] = {
    State402.FAULT: Command402.FAULT_RESET,
    State402.SWITCH_ON_DISABLED: Command402.SHUTDOWN,
    State402.READY_TO_SWITCH_ON: Command402.SWITCH_ON,
    State402.SWITCHED_ON: Command402.ENABLE_OPERATION,
    State402.QUICK_STOP_ACTIVE: Command402.DISABLE_VOLTAGE,
}


def decode_statusword(statusword: int) -> State402:
    """State encoded in a CiA 402 statusword (0x6041)."""
    for state, (mask, value) in STATUSWORD_PATTERNS.items():
        if statusword & mask == value:
            return state
    raise ValueError(f"statusword 0x{statusword:04X} encodes no CiA 402 state")


def encode_statusword(state: State402, extra_bits: int = STATUSWORD_REMOTE) -> int:
    """Statusword a device in `state` reports (remote bit set by default)."""
    _, value = STATUSWORD_PATTERNS[state]
    voltage = (
        STATUSWORD_VOLTAGE_ENABLED
        if state in TORQUE_STATES | {State402.SWITCHED_ON, State402.READY_TO_SWITCH_ON}
        else 0
    )
    return value | voltage | extra_bits


def decode_controlword(controlword: int) -> Command402 | None:
    """Command a controlword (0x6040) carries, per the CiA 402 command coding table: the fault reset
    bit (7) first, then enable voltage (bit 1) and quick stop (bit 2, active low), then bits 0-3."""
    if controlword & CONTROLWORD[Command402.FAULT_RESET]:
        return Command402.FAULT_RESET
    if controlword & _CW_ENABLE_VOLTAGE == 0:
        return Command402.DISABLE_VOLTAGE
    if controlword & _CW_QUICK_STOP_OFF == 0:
        return Command402.QUICK_STOP
    # 'disable operation' has the coding of 'switch on': it decodes as SWITCH_ON
    return _COMMAND_BY_LOW_BITS.get(controlword & _CW_COMMAND_BITS)


_CW_ENABLE_VOLTAGE = 1 << 1
_CW_QUICK_STOP_OFF = 1 << 2
_CW_COMMAND_BITS = 0x0F
_COMMAND_BY_LOW_BITS = {
    CONTROLWORD[c]: c for c in (Command402.SHUTDOWN, Command402.SWITCH_ON, Command402.ENABLE_OPERATION)
}
