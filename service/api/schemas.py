"""Request schemas (the Create family) and the error answer; the Public family lives in service/api/public/.

A request names its method and carries that method's options: a discriminated union built from the
method registry, so /docs lists every method's options with their bounds and units, and a new
method appears here by being registered. `method` may be left out: it defaults to "adaptive".
"""

from __future__ import annotations

from typing import Annotated, Any, Literal, Union

from pydantic import (
    AfterValidator,
    BaseModel,
    ConfigDict,
    Discriminator,
    Field,
    Tag,
    create_model,
    field_validator,
    model_validator,
)

from service.identification.orders import MAX_ORDER, MAX_ORDERS, distinct_orders
from service.identification.registry import METHODS
from service.model.operating_point import OperatingPoint
from service.names import MAX_NAME_LENGTH, check_name
from service.runs.plans import Grid, RegimePlacement
from service.runs.schedules import check_cron, check_timezone
from service.runs.validation import ValidationOptions

MethodName = Literal[tuple(METHODS)]
DEFAULT_METHOD = "adaptive"

# the bench a run is for, in a lab of several benches on one database (service/runs/lab.py)
BENCH_DESCRIPTION = (
    "the bench it runs on (GET /benches); default: this service's own bench. Another bench's run is stored "
    "and waits for that bench's service (its answer says what it waits for). Printable text: no control "
    "characters, no whitespace at either end"
)
# names are stored and shown lab-wide: printable text on both engines (service/names.py), else a 422 saying why
BenchName = Annotated[
    str,
    Field(min_length=1, max_length=MAX_NAME_LENGTH, description=BENCH_DESCRIPTION),
    AfterValidator(lambda v: check_name(v, "bench name")),
]
ScheduleName = Annotated[
    str,
    Field(
        min_length=1,
        max_length=MAX_NAME_LENGTH,
        description="unique among the schedules. Printable text: no control characters, no whitespace at either end",
    ),
    AfterValidator(lambda v: check_name(v, "schedule name")),
]


# the methods that cancel several orders at once (their options carry `orders`); the first is the one a request
# naming several orders and no method gets
SEVERAL_ORDERS_METHODS = [name for name, m in METHODS.items() if "orders" in m.options_model.model_fields]
ORDERS_DESCRIPTION = (
    f"harmonic orders cancelled at each point (DESIGN section 6; 1..{MAX_ORDER}, at most {MAX_ORDERS}, this bench's "
    "harmonic order among them); default that order alone. Several need a method that cancels several at once "
    f"({', '.join(SEVERAL_ORDERS_METHODS)}: the method when none is named); for it, the same as options.orders"
)


def _method_of(value: Any) -> str:
    """The union's tag: the `method` of a request body (or model); left out, "adaptive", or the method of several
    orders when the body names several."""
    if isinstance(value, dict):
        orders = value.get("orders")
        several = isinstance(orders, list) and len(orders) > 1 and SEVERAL_ORDERS_METHODS
        return value.get("method", SEVERAL_ORDERS_METHODS[0] if several else DEFAULT_METHOD)
    return getattr(value, "method", DEFAULT_METHOD)


def _orders_checked(method: str) -> Any:
    """The `orders` field's validator of one method's variant: distinct, and one order for a method of one."""

    def check(orders: list[int] | None) -> list[int] | None:
        if orders is None:
            return None
        distinct_orders(orders)
        if len(orders) > 1 and method not in SEVERAL_ORDERS_METHODS:
            raise ValueError(
                f"orders {orders}: method {method} cancels one order; {' or '.join(SEVERAL_ORDERS_METHODS)} cancels "
                "several at once"
            )
        return orders

    return field_validator("orders")(lambda cls, orders: check(orders))


def _orders_into_options(self: Any) -> Any:
    """A method of several orders takes the request's `orders` as its options.orders (one statement of them)."""
    if self.orders is not None and "orders" in type(self.options).model_fields:
        if "orders" in self.options.model_fields_set and self.options.orders != self.orders:
            raise ValueError(f"orders {self.orders} and options.orders {self.options.orders} differ: give one")
        self.options = self.options.model_copy(update={"orders": list(self.orders)})
    return self


def _per_method(kind: str, fields: dict[str, Any], example: dict) -> Any:
    """Annotated union of one model per registered method: `{kind}` fields + orders + method + its options."""
    variants = []
    for name, method in METHODS.items():
        model = create_model(
            f"{name.capitalize()}{kind}Create",
            __config__=ConfigDict(extra="forbid", json_schema_extra={"examples": [{**example, "method": name}]}),
            __doc__=f"{kind} with the {method.display_name} method: {method.summary}.",
            __validators__={
                "orders_checked": _orders_checked(name),
                "orders_into_options": model_validator(mode="after")(_orders_into_options),
            },
            **fields,
            orders=(
                list[Annotated[int, Field(ge=1, le=MAX_ORDER)]] | None,
                Field(None, min_length=1, max_length=MAX_ORDERS, description=ORDERS_DESCRIPTION),
            ),
            # required but for the default method and that of several orders: a body without it is one of these
            # two variants (_method_of), as documented
            method=(
                Literal[name],
                Field(
                    name if name in (DEFAULT_METHOD, SEVERAL_ORDERS_METHODS[0]) else ...,
                    description=method.display_name,
                ),
            ),
            options=(method.options_model, Field(default_factory=method.options_model)),
        )
        variants.append(Annotated[model, Tag(name)])
    return Annotated[Union[tuple(variants)], Discriminator(_method_of)]


IdentificationCreate = _per_method(
    "Identification",
    {"operating_point": (OperatingPoint, ...), "bench": (BenchName | None, None)},
    {"operating_point": {"torque_nm": 2.5, "speed_rpm": 2000, "udc_v": 12}, "options": {}},
)

SweepCreate = _per_method(
    "Sweep",
    {
        "grid": (Grid, ...),
        "bench": (BenchName | None, None),
        "confirm_large": (
            bool,
            Field(
                False,
                description="required for a grid above "
                "safety.max_sweep_points_unconfirmed points (a run of "
                "hours is started on purpose)",
            ),
        ),
        "regime": (
            RegimePlacement | None,
            Field(
                None,
                description="place speed values around the predicted "
                "field-weakening onset of each torque "
                "(service.runs.plans.plan_grid); the sweep stores and measures the planned grid (POST "
                "/sweeps/preview shows it)",
            ),
        ),
    },
    {"grid": {"torque_nm": [1, 2.5, 4], "speed_rpm": [1000, 2000, 2500], "udc_v": [12]}},
)


_SCHEDULE_EXAMPLE = {
    "name": "nightly OP map",
    "cron": "0 2 * * 1-5",
    "timezone": "Europe/Berlin",
    "sweep": {"grid": {"torque_nm": [1, 2.5, 4], "speed_rpm": [1000, 2000], "udc_v": [12]}, "method": "adaptive"},
    "enabled": True,
}
_CRON = (
    "cron in 5 fields: minute hour day-of-month month day-of-week, Debian cron semantics (across DST a time "
    "that does not exist runs once right after the change, a time that repeats runs once)"
)


class _ScheduleFields(BaseModel):
    @field_validator("cron", check_fields=False)
    @classmethod
    def _cron(cls, value: str) -> str:
        return check_cron(value)

    @field_validator("timezone", check_fields=False)
    @classmethod
    def _zone(cls, value: str) -> str:
        check_timezone(value)
        return value


class ScheduleCreate(_ScheduleFields):
    """A sweep submitted at the times of a cron expression; `sweep` is checked exactly as POST /sweeps is."""

    model_config = ConfigDict(extra="forbid", json_schema_extra={"examples": [_SCHEDULE_EXAMPLE]})
    name: ScheduleName
    cron: str = Field(..., min_length=1, max_length=200, description=_CRON)
    timezone: str = Field("UTC", min_length=1, max_length=64, description="IANA time zone, e.g. Europe/Berlin")
    sweep: SweepCreate
    enabled: bool = True
    bench: BenchName | None = Field(None, description="the bench whose service fires it; default this service's")


class ScheduleUpdate(_ScheduleFields):
    """The fields to change; the others stay. A new cron or zone, or enabling, counts from now."""

    model_config = ConfigDict(extra="forbid", json_schema_extra={"examples": [{"enabled": False}]})
    name: ScheduleName = None
    cron: str = Field(None, min_length=1, max_length=200, description=_CRON)
    timezone: str = Field(None, min_length=1, max_length=64, description="IANA time zone")
    sweep: SweepCreate = None
    enabled: bool = None


class ValidationCreate(BaseModel):
    """Validate a map in the drive's LUT mode: its LUT is downloaded first (CRC-32 read back)."""

    model_config = ConfigDict(extra="forbid", json_schema_extra={"examples": [{"force": False, "options": {}}]})
    force: bool = Field(False, description="validate a partial map (cells not ok carry no injection)")
    options: ValidationOptions = Field(default_factory=ValidationOptions)
    bench: BenchName | None = None


class ErrorPublic(BaseModel):
    """Every refusal except 422 (which lists one item per field, see HTTPValidationError)."""

    detail: str = Field(..., description="what was refused and why")
