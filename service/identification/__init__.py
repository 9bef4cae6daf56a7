"""Identification of the compensation theta* at one operating point: adaptive (paper), grid (paper's
cross-check) and, later, probe (ours). Each method is a pure algorithm over a `MeasurementSession`
(session.py) so it runs the same against the emulator, a real bench, or a closed-form plant."""
from service.identification.result import IdentificationResult, METHODS
from service.identification.adaptive import AdaptiveOptions, identify_adaptive
from service.identification.grid import GridOptions, identify_grid
from service.identification.probe import ProbeOptions, identify_probe

__all__ = ["IdentificationResult", "METHODS", "AdaptiveOptions", "identify_adaptive", "GridOptions", "identify_grid",
           "ProbeOptions", "identify_probe"]
