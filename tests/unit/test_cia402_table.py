"""drivers/cia402.py against canopen's CiA 402 table (canopen.profiles.p402.State402), the one definition
of the statusword masks and controlwords that the master (drivers/cia402_master.py) and the emulated
devices (plant_emulator/cia402_device.py) both use."""

from __future__ import annotations

from canopen.profiles.p402 import State402 as P402

from drivers.cia402 import (
    CONTROLWORD,
    DEVICE_TRANSITIONS,
    STATUSWORD_PATTERNS,
    Command402,
    State402,
    decode_controlword,
    decode_statusword,
    encode_statusword,
)

# canopen's transitions our devices do not make: the automatic ones (no controlword: power-up, the end of
# a fault reaction) and 16, quick stop back to operation, which CiA 402 leaves optional (our drive and load
# end a quick stop in SWITCH_ON_DISABLED only)
NOT_COMMANDED = {("START", "NOT READY TO SWITCH ON"), ("NOT READY TO SWITCH ON", "SWITCH ON DISABLED")}
NOT_COMMANDED |= {("FAULT REACTION ACTIVE", "FAULT"), ("QUICK STOP ACTIVE", "OPERATION ENABLED")}


def _state(canopen_name: str) -> State402:
    return State402[canopen_name.replace(" ", "_")]


def test_every_state_has_canopens_pattern_and_each_statusword_at_most_one_state():
    assert {_state(name): pattern for name, pattern in P402.SW_MASK.items()} == STATUSWORD_PATTERNS
    assert set(STATUSWORD_PATTERNS) == set(State402)
    for word in range(1 << 16):
        matches = [s for s, (mask, value) in STATUSWORD_PATTERNS.items() if word & mask == value]
        assert len(matches) <= 1, f"statusword 0x{word:04X} matches {matches}"


def test_what_a_device_reports_decodes_to_its_state():
    for state in State402:
        assert decode_statusword(encode_statusword(state)) is state


def test_each_command_word_decodes_to_its_command():
    for command, word in CONTROLWORD.items():
        expected = Command402.SWITCH_ON if command is Command402.DISABLE_OPERATION else command  # same coding
        assert decode_controlword(word) is expected


def test_the_devices_make_every_transition_canopens_master_commands():
    for (start, end), word in P402.TRANSITIONTABLE.items():
        if (start, end) in NOT_COMMANDED:
            continue
        command = decode_controlword(word)
        assert DEVICE_TRANSITIONS.get((_state(start), command)) is _state(end), (start, end, hex(word))
