"""Identification of the compensation theta* at one operating point: adaptive (paper), probe and grid
(the paper's cross-check). Each method is a pure algorithm over a `MeasurementSession` (session.py)
so it runs the same against the emulator, a real bench, or a closed-form plant; `registry.METHODS`
names them."""

from service.identification.adaptive import AdaptiveOptions, identify_adaptive
from service.identification.grid import GridOptions, identify_grid
from service.identification.probe import ProbeOptions, identify_probe
from service.identification.registry import METHODS, Method
from service.identification.result import IdentificationResult

__all__ = [
    "IdentificationResult",
    "METHODS",
    "Method",
    "AdaptiveOptions",
    "identify_adaptive",
    "GridOptions",
    "identify_grid",
    "ProbeOptions",
    "identify_probe",
]
