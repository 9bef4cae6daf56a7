"""The one registry of identification methods (as python-can's BACKENDS names its transports): the
API's request schemas, the CLI's choices, the dashboard (GET /api/v1/methods) and the docs read it.
A new method is one entry here: its options model and the function that runs it over a
MeasurementSession (session.py) with the signature of identify_probe."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable

from pydantic import BaseModel

from service.identification.adaptive import AdaptiveOptions, identify_adaptive
from service.identification.grid import GridOptions, identify_grid
from service.identification.orders import OrdersOptions, identify_orders
from service.identification.probe import ProbeOptions, identify_probe


@dataclass(frozen=True)
class Method:
    name: str
    display_name: str
    summary: str
    options_model: type[BaseModel]
    run: Callable[..., Any]


METHODS: dict[str, Method] = {
    m.name: m
    for m in (
        Method(
            "adaptive",
            "adaptive filter (paper eq. 16)",
            "the paper's adaptive filter in block form; S_hat from eq. 14-20, replaced online by the measured S",
            AdaptiveOptions,
            identify_adaptive,
        ),
        Method(
            "probe",
            "probe + Newton",
            "two probe injections measure S as a 2x2; Newton steps with Broyden updates land on theta*",
            ProbeOptions,
            identify_probe,
        ),
        Method(
            "probe-orders",
            "probe + Newton, several orders",
            "every order of `orders` (the 6th and 12th by default) cancelled at once: probes measure the whole "
            "Jacobian with the cross-paths between orders; joint Newton steps with Broyden updates",
            OrdersOptions,
            identify_orders,
        ),
        Method(
            "grid",
            "grid search (paper Fig. 8)",
            "the paper's grid of gamma x delta, its minimum and an affine least-squares fit",
            GridOptions,
            identify_grid,
        ),
    )
}
