"""CiA 402 power drive state machine: one table, used by both sides of the wire.

The drive firmware in plant_emulator walks `DEVICE_TRANSITIONS`; the master in drivers/ decodes the
statusword with `decode_statusword` and follows `PATH_TO_OPERATION_ENABLED`. Bit patterns are those of
CiA 402 (IEC 61800-7-201), section "Statusword" and "Controlword".
"""

from __future__ import annotations

from enum import Enum


class State402(str, Enum):
    NOT_READY_TO_SWITCH_ON = "not_ready_to_switch_on"
    SWITCH_ON_DISABLED = "switch_on_disabled"
    READY_TO_SWITCH_ON = "ready_to_switch_on"
    SWITCHED_ON = "switched_on"
    OPERATION_ENABLED = "operation_enabled"
    QUICK_STOP_ACTIVE = "quick_stop_active"
    FAULT_REACTION_ACTIVE = "fault_reaction_active"
    FAULT = "fault"


# statusword (mask, value) per state
STATUSWORD_PATTERNS: dict[State402, tuple[int, int]] = {
    State402.NOT_READY_TO_SWITCH_ON: (0x4F, 0x00),
    State402.SWITCH_ON_DISABLED: (0x4F, 0x40),
    State402.READY_TO_SWITCH_ON: (0x6F, 0x21),
    State402.SWITCHED_ON: (0x6F, 0x23),
    State402.OPERATION_ENABLED: (0x6F, 0x27),
    State402.QUICK_STOP_ACTIVE: (0x6F, 0x07),
    State402.FAULT_REACTION_ACTIVE: (0x4F, 0x0F),
    State402.FAULT: (0x4F, 0x08),
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


# controlword value the master sends for each command
CONTROLWORD: dict[Command402, int] = {
    Command402.SHUTDOWN: 0x0006,
    Command402.SWITCH_ON: 0x0007,
    Command402.ENABLE_OPERATION: 0x000F,
    Command402.DISABLE_VOLTAGE: 0x0000,
    Command402.QUICK_STOP: 0x0002,
    Command402.DISABLE_OPERATION: 0x0007,
    Command402.FAULT_RESET: 0x0080,
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
    """Command a controlword (0x6040) carries, per the CiA 402 command coding table."""
    if controlword & 0x80:
        return Command402.FAULT_RESET
    if controlword & 0x02 == 0:
        return Command402.DISABLE_VOLTAGE
    if controlword & 0x04 == 0:
        return Command402.QUICK_STOP
    if controlword & 0x0F == 0x06:
        return Command402.SHUTDOWN
    if controlword & 0x0F == 0x07:
        return Command402.SWITCH_ON  # also 'disable operation' (same coding)
    if controlword & 0x0F == 0x0F:
        return Command402.ENABLE_OPERATION
    return None
