"""Exceptions of the drivers: one family per wire, each message says what was attempted and why it failed.

The service turns these into failed jobs and operator messages, so a message must be readable without
the traceback: which node, which object (index:sub and its EDS name), which value, and what the device
or the transport said (SDO abort code with its meaning, samples that arrived, the reply received).
"""

from __future__ import annotations


class DriverError(Exception):
    """Base class of every error raised by drivers/."""


class NotConnectedError(DriverError):
    """A driver method was called before connect() (or after disconnect())."""


# --- CANopen ---------------------------------------------------------------------------------------


class SdoError(DriverError):
    """An SDO read or write of one object failed.

    Attributes name the object so that callers can react to specific objects or abort codes
    (e.g. 0x06090030 'value range exceeded' on the target torque).
    """

    def __init__(
        self,
        node_id: int,
        action: str,
        index: int,
        subindex: int,
        name: str,
        detail: str,
        abort_code: int | None = None,
        value: object = None,
    ):
        self.node_id = node_id
        self.action = action
        self.index = index
        self.subindex = subindex
        self.object_name = name
        self.abort_code = abort_code
        self.value = value
        what = f"SDO {action} of 0x{index:04X}:{subindex:02X} '{name}'"
        if action == "write" and value is not None:
            what += f" = {value!r}"
        super().__init__(f"node {node_id}: {what} failed: {detail}")


class SdoAbortError(SdoError):
    """The device answered with an SDO abort (it refused the access)."""


class SdoTimeoutError(SdoError, TimeoutError):
    """The device did not answer the SDO request in time (wrong node id, node absent, bus down)."""


class StateTransitionError(DriverError, TimeoutError):
    """A CiA 402 state change did not happen within its timeout."""


class ForeignMasterError(DriverError):
    """Another master uses our node id on the CAN bus (its heartbeat was heard on our own COB-ID)."""


class FaultReactionActiveError(StateTransitionError):
    """A fault reset found the device still in its fault reaction (FAULT_REACTION_ACTIVE, e.g. a load
    machine braking to standstill) after waiting for it to end: try again once it has."""


class HeartbeatMissingError(DriverError, TimeoutError):
    """The device answered on the bus but its heartbeat (0x700 + node id) was not heard in time."""


class DriveFaultError(DriverError):
    """The device is in FAULT; the message names its error code. Only a fault reset clears it."""


class WrongDeviceError(DriverError):
    """The node answers with another identity (0x1018) than the device its EDS describes (node ids
    swapped, or another device at this id): nothing was written to it."""


class ConfigurationError(DriverError):
    """The device reports a configuration the driver cannot work with (e.g. rated torque 0)."""


# --- DAQ stream ------------------------------------------------------------------------------------


class DaqError(DriverError):
    """Base class of DAQ stream errors."""


class DaqTimeout(DaqError, TimeoutError):
    """Fewer samples than requested arrived before the timeout."""


class DaqDisconnected(DaqError, ConnectionError):
    """The reader thread stopped: port closed, EOF, or an OS error on read."""


class DaqPortBusy(DaqError):
    """The DAQ port is held (exclusively locked) by another reader: one reader per DAQ."""


class DaqRateMismatch(DaqError):
    """The DAQ streams at another frame rate than the one it is configured at (measured at connect)."""

    def __init__(self, message: str, measured_hz: float, expected_hz: float):
        super().__init__(message)
        self.measured_hz = measured_hz
        self.expected_hz = expected_hz


class DaqNotSerialPort(DaqError):
    """The DAQ path names something that cannot be a serial port (a regular file, /dev/null, ...)."""


class DaqNotStreaming(DaqError, TimeoutError):
    """The DAQ port opened but no frame arrived (a silent port, or not the DAQ's)."""


# --- DC supply (SCPI) ------------------------------------------------------------------------------


class ScpiError(DriverError):
    """The supply's reply was missing, garbled or disagreed with the command."""


class ScpiTimeout(ScpiError, TimeoutError):
    """No complete reply line arrived within the timeout."""
