"""Request-validation items said in the service's words (service/validation_words.py, issue 30): the
field's JSON path and the bound in every message, no library text. The whole API is checked by the
schemathesis pass (tests/protocol/test_api_schemathesis.py assert_refusal_in_our_words)."""

from __future__ import annotations

import pytest

from service.validation_words import in_our_words


@pytest.mark.parametrize(
    "error, loc, said",
    [
        (
            {"type": "greater_than", "ctx": {"gt": 0.0}, "msg": "Input should be greater than 0"},
            ["body", "operating_point", "speed_rpm"],
            "operating_point.speed_rpm must be greater than 0",
        ),
        ({"type": "less_than_equal", "ctx": {"le": 80}}, ["body", "target_db"], "target_db must be at most 80"),
        (
            {"type": "model_attributes_type", "msg": "Input should be a valid dictionary"},
            ["body", "regime"],
            "regime must be an object",
        ),
        (
            {
                "type": "datetime_from_date_parsing",
                "msg": "Input should be a valid datetime or date, input is too short",
            },
            ["query", "start"],
            "start must be a date and time in ISO 8601, e.g. 2026-11-27T22:00:00+01:00",
        ),
        # a kind nobody listed: the library's phrase said as ours, after the field
        ({"type": "uuid_parsing", "msg": "Input should be a valid UUID"}, ["body", "id"], "id must be a valid UUID"),
        # our own validator's message: pydantic's prefix off, the field put first where the message does not say it
        (
            {"type": "value_error", "msg": "Value error, unknown time zone '0': use an IANA name such as UTC"},
            ["body", "timezone"],
            "timezone: unknown time zone '0': use an IANA name such as UTC",
        ),
        (
            {"type": "value_error", "msg": "Value error, values must be unique"},
            ["body", "grid", "speed_rpm"],
            "grid.speed_rpm: values must be unique",
        ),
    ],
)
def test_each_kind_names_the_field_in_our_words(error, loc, said):
    assert in_our_words(error, loc) == said
