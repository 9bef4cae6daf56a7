"""Schemathesis against the real app's /openapi.json: no request it generates gets a 5xx, every
status it gets is documented, every answer matches its documented schema.

Bounded and repeatable: positive and negative generation, at most MAX_EXAMPLES cases per operation and
mode (fewer negative ones: the suite keeps to its 15 minutes), derandomized (the seed follows the test's
code, so the figures change only with it), no example database, no deadline (2 shared cores). It runs
with an OPERATOR token so generated bodies reach validation past the 401/403 (negative mode also mangles
the token: those get 401). The documented request examples go first and are accepted (202); every
accepted run is cancelled through the API at once, so the bench is never busy for more than one operating
point's set-up and make_safe. The missing / viewer token cases are in test_api_contract and
test_api_input.
`GET /events` is left out: it is an endless Server-Sent Events stream.

Figures: .venv/bin/python -m pytest -q -s tests/protocol/test_api_schemathesis.py  (prints requests and 5xx)
"""

import json
from collections import Counter

import pytest
import schemathesis
from hypothesis import HealthCheck, Phase, given, settings
from hypothesis.errors import Unsatisfiable
from schemathesis import GenerationMode
from schemathesis.checks import not_a_server_error
from schemathesis.specs.openapi.checks import (
    content_type_conformance,
    negative_data_rejection,
    response_schema_conformance,
    status_code_conformance,
)

from tests.support.live_app import wait_finished

MAX_EXAMPLES = {GenerationMode.POSITIVE: 40, GenerationMode.NEGATIVE: 25}
# negative cases mangle the token hundreds of times from one client: the throttle (proven in
# tests/protocol/test_auth_throttle.py) would answer the later cases 429
LIVE_SETTINGS = {"server.auth_max_failures": 1_000_000}
CHECKS = [
    not_a_server_error,
    status_code_conformance,
    content_type_conformance,
    response_schema_conformance,
    negative_data_rejection,
]
TALLY: Counter = Counter()


@pytest.fixture(scope="module")
def live(live):
    """The shared `live` (tests/conftest.py) with something to find: a finished 1-point sweep gives a job,
    a result, a sweep and a map with id 1; the tally printed at the end."""
    _, client, operator = live
    r = client.post(
        "/api/v1/sweeps",
        headers=operator,
        json={"grid": {"torque_nm": [2.5], "speed_rpm": [2000], "udc_v": [12]}, "method": "adaptive"},
    )
    assert r.status_code == 202, r.text
    wait_finished(client, f"/api/v1/sweeps/{r.json()['id']}")
    yield live
    summary = "\n  ".join(f"{k}: {v}" for k, v in sorted(TALLY.items()))
    requests = sum(v for k, v in TALLY.items() if k.startswith("status"))
    print(f"\nschemathesis: {requests} requests, {TALLY['status 5xx']} with a 5xx\n  {summary}")


def operations(client):
    schema = schemathesis.openapi.from_asgi("/openapi.json", client.app).exclude(path="/api/v1/events")
    return schema, [result.ok() for result in schema.get_all_operations()]


# One test per generation mode, looping over the operations itself: schemathesis' lazy pytest
# fixture (schemathesis.pytest.from_fixture) fails on pytest 9 ('Function' has no '_nodeid').
@pytest.mark.parametrize("mode", [GenerationMode.POSITIVE, GenerationMode.NEGATIVE])
def test_no_server_errors(live, mode):
    _, client, operator = live
    failures = []
    schema, ops = operations(client)
    # the documented examples first (they reach the 202 path), then generated cases
    plan = [
        (op, strategy, 1)
        for op in ops
        for strategy in (schema.get_strategies_from_examples(op) if mode == GenerationMode.POSITIVE else [])
    ]
    plan += [(op, op.as_strategy(generation_mode=mode), MAX_EXAMPLES[mode]) for op in ops]
    for operation, strategy, examples in plan:

        @given(case=strategy)
        @settings(
            max_examples=examples,
            derandomize=True,
            database=None,
            deadline=None,
            phases=[Phase.explicit, Phase.generate],
            suppress_health_check=list(HealthCheck),
        )
        def run(case):
            response = case.call(headers=operator)
            TALLY[f"status {response.status_code // 100}xx"] += 1  # counted before the checks can fail
            TALLY[f"{operation.label} {response.status_code}"] += 1
            case.validate_response(response, checks=CHECKS, headers=operator)
            if 400 <= response.status_code < 500:
                assert_refusal_in_our_words(response)
            if response.status_code == 201 and case.path == "/api/v1/schedules":
                # a schedule was made: delete it before it fires (every-minute crons are generated too)
                TALLY["schedules created and deleted"] += 1
                gone = client.delete(f"/api/v1/schedules/{response.json()['id']}", headers=operator)
                assert gone.status_code == 204, gone.text
            if response.status_code == 202:  # a run was accepted: stop it before it occupies the bench
                TALLY["runs accepted and cancelled"] += 1
                kind = "sweeps" if case.path.endswith("sweeps") else "jobs"  # identifications, map validations
                cancel = client.post(f"/api/v1/{kind}/{response.json()['id']}/cancel", headers=operator)
                assert cancel.status_code in (200, 409), cancel.text

        try:
            run()
        except Unsatisfiable:  # negative mode: an operation without parameters has no invalid input
            TALLY["operations without negative cases"] += 1
        except Exception as exc:  # keep going: one report naming every operation that failed
            failures.append(f"{operation.label}: {exc}")
    assert not failures, "\n\n".join(failures)


LIBRARY_WORDS = ("pydantic", "validation error for", "input should", "type=", "input_value", "further information")


def assert_refusal_in_our_words(response) -> None:
    """Issue 30: a 4xx says what was wrong in the service's words; a request-validation item names its field
    (`loc`, its JSON path inside the body, query or path) in its message, and no library's text or URL."""
    try:
        body = response.json()
    except ValueError:
        raise AssertionError(f"a {response.status_code} without a JSON body: {response.text[:200]!r}") from None
    detail = body.get("detail") if isinstance(body, dict) else None
    assert detail, f"a {response.status_code} that says nothing: {body!r}"
    items = detail if isinstance(detail, list) else [{"msg": detail}]
    for item in items:
        said = json.dumps({k: v for k, v in item.items() if k != "input"})  # the echoed input is the caller's own
        assert "https://" not in said and "http://" not in said, said
        assert not any(w in said.lower() for w in LIBRARY_WORDS), said
        if response.status_code == 422 and isinstance(detail, list):
            loc = item.get("loc")
            assert isinstance(loc, list) and loc and loc[0] in ("body", "query", "path", "header"), item
            field = ".".join(str(p) for p in loc[1:])
            assert not field or field in item["msg"] or str(loc[-1]) in item["msg"], item
