"""One error root for the service (service/errors.py): every kind has one HTTP status, every error a
layer raises resolves to one of them, the one handler answers that status, and no route holds a `try`."""

from __future__ import annotations

import ast
import importlib
import pkgutil
from pathlib import Path

import pytest
from fastapi import FastAPI, Request
from fastapi.testclient import TestClient

import service
from service.api.errors import _DESCRIPTIONS, ANSWERED_KINDS, ErrorAnswers, service_error, value_error
from service.api.refusals import refusals_at
from service.errors import KINDS, Invalid, NotFound, ServiceError

ROUTES = Path(service.__file__).parent / "api" / "routes"


def _all_service_modules() -> None:
    """Import every module of service/ so every error class it declares is a subclass we can see."""
    for info in pkgutil.walk_packages(service.__path__, "service."):
        if not info.name.startswith(("service.paper", "service.cli")):  # entry points: they declare no kinds
            importlib.import_module(info.name)


def _subclasses(cls: type) -> set[type]:
    found = set(cls.__subclasses__())
    for sub in list(found):
        found |= _subclasses(sub)
    return found


def test_no_route_holds_a_try():
    """Routes say what to do; what a refusal answers is declared once (service/errors.py + one handler)."""
    offenders = [
        f"{path.name}:{node.lineno}"
        for path in sorted(ROUTES.glob("*.py"))
        for node in ast.walk(ast.parse(path.read_text(), str(path)))
        if isinstance(node, (ast.Try, ast.TryStar))
    ]
    assert offenders == [], f"routes with try (raise a ServiceError kind from the service layer): {offenders}"


def test_every_kind_has_one_documented_status():
    statuses = {kind: kind.http_status for kind in KINDS}
    assert all(code in _DESCRIPTIONS or code == 422 for code in statuses.values()), statuses
    assert ServiceError.http_status == 500  # the bare root is a fault of the service


def test_every_service_error_resolves_to_one_kind():
    """A class under two kinds with different statuses would answer by the order of its bases: refused."""
    _all_service_modules()
    for cls in _subclasses(ServiceError):
        kinds = {k for k in KINDS if issubclass(cls, k)}
        assert kinds, f"{cls.__module__}.{cls.__qualname__} derives from the root but from no kind"
        assert len({k.http_status for k in kinds}) == 1, f"{cls.__qualname__}: kinds {kinds} disagree"
        assert cls.http_status == next(iter(kinds)).http_status, cls


@pytest.fixture
def client():
    app = FastAPI()
    for kind in ANSWERED_KINDS:
        app.add_exception_handler(kind, service_error)
    app.add_exception_handler(ValueError, value_error)
    app.add_middleware(ErrorAnswers)
    raised: dict[str, Exception] = {}

    @app.get("/plain")
    def plain():
        raise raised["exc"]

    @app.get("/declared", dependencies=[refusals_at(["body", "grid"], confirm_large=["body", "confirm_large"])])
    def declared(request: Request):
        raise raised["exc"]

    with TestClient(app, raise_server_exceptions=False) as c:
        yield c, raised


@pytest.mark.parametrize("kind", KINDS, ids=lambda k: k.__name__)
def test_the_one_handler_answers_each_kinds_status(client, kind):
    c, raised = client
    raised["exc"] = kind("what was wrong and how to fix it")
    answer = c.get("/declared")
    assert answer.status_code == kind.http_status
    if kind is Invalid:
        assert answer.json() == {
            "detail": [{"loc": ["body", "grid"], "msg": "what was wrong and how to fix it", "type": "value_error"}]
        }
    elif answer.status_code != 503:
        assert answer.json() == {"detail": "what was wrong and how to fix it"}
    else:
        assert answer.headers["retry-after"] == "5"


def test_a_refusal_names_the_part_the_route_declares(client):
    c, raised = client
    raised["exc"] = Invalid("too many points", at="confirm_large")
    assert c.get("/declared").json()["detail"][0]["loc"] == ["body", "confirm_large"]
    raised["exc"] = Invalid("torque too high", problems=(("torque_nm", "above 10 N m"),), at="regime")
    assert c.get("/declared").json()["detail"][0]["loc"] == ["body", "grid", "torque_nm"]  # not declared: subject


def test_not_found_reads_as_its_message_and_is_still_a_key_error():
    exc = NotFound("job 7 does not exist")
    assert str(exc) == "job 7 does not exist" and isinstance(exc, KeyError)


def test_the_bare_root_and_a_plain_value_error_off_a_declared_route_are_faults(client):
    c, raised = client
    raised["exc"] = ServiceError("a bug")
    assert c.get("/plain").status_code == 500 and "error_id" in c.get("/plain").json()
    raised["exc"] = ValueError("a bug")
    assert c.get("/plain").status_code == 500
    assert c.get("/declared").status_code == 422  # a declared route: the request's subject at fault
