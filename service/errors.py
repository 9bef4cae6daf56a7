"""The service's one error root and its kinds, each with its HTTP meaning declared here once.

Floor 0 (beside settings): every layer may raise a kind; the API registers one handler for the root
(service/api/errors.py) and answers `kind.http_status`. A layer's own error derives from the kind that says
what it means to a caller (and may keep its historical base too: `class LimitError(Invalid, ValueError)`).
Anything that is not a ServiceError is a fault of the service (500, with its traceback in the log)."""

from __future__ import annotations

import contextlib
from typing import ClassVar, Iterator


class ServiceError(Exception):
    """The root: an outcome the service expects in the normal course (a refusal, a missing resource, a bench
    or database that cannot do it now), said in one line a test engineer can act on."""

    http_status: ClassVar[int] = 500


class NotFound(ServiceError, KeyError):
    """No such resource (404). A KeyError too, for callers that looked it up in a mapping; str() is the
    message (KeyError's would quote it)."""

    http_status = 404

    def __str__(self) -> str:
        return str(self.args[0]) if self.args else ""


class Conflict(ServiceError):
    """The resource's state does not allow this now (409): a finished job, a taken name, a busy bench."""

    http_status = 409


class BenchRefused(Conflict):
    """The bench refused or could not start the work (409): not reached, an interlock tripped."""


class BenchFailed(ServiceError):
    """The bench or the drive failed doing it, or did not answer (502)."""

    http_status = 502


class Invalid(ServiceError):
    """The request asks for something the service will not do (422). `at` names the part of the request at
    fault as the route declares it (service/api/refusals.py: "subject", "options", "confirm_large", ...);
    `problems` pairs a field under it with what is wrong, one 422 item each (none: one item at `at`)."""

    http_status = 422
    at: str = "subject"
    error_type: str = "value_error"  # the 422 item's type

    def __init__(self, message: str, problems: tuple[tuple[str, str], ...] = (), at: str | None = None):
        super().__init__(message)
        self.problems = problems
        if at is not None:
            self.at = at


class Unavailable(ServiceError):
    """What is needed (the database) cannot be used now, for a reason that passes (503 with Retry-After)."""

    http_status = 503
    retry_after_s: float = 5.0


# the kinds a handler maps to a status: each exactly one (tests/unit/test_service_errors.py)
KINDS: tuple[type[ServiceError], ...] = (NotFound, Conflict, BenchRefused, BenchFailed, Invalid, Unavailable)


@contextlib.contextmanager
def not_found(message: str) -> Iterator[None]:
    """A KeyError from below (a lookup that found nothing) becomes NotFound saying what does not exist."""
    try:
        yield
    except KeyError:
        raise NotFound(message) from None
