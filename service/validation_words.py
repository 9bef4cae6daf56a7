"""A pydantic validation item said in the service's words (issue 30: no library text reaches a user): the field
it is about (its path inside the body, query or path: `loc` without its first part) and the bound that applies.
The API's 422 items (service/api/errors.py) and the CLI's refusals (service/cli) say the same."""

from __future__ import annotations

from typing import Any


def in_our_words(e: dict[str, Any], loc: list[str | int]) -> str:
    """`e` (one item of a pydantic ValidationError) at `loc` (body, query or path first) in the service's words
    (module doc); a kind not listed: the library's "Input should ..." as "must ...", any other message (our own
    validators') after its field where it does not name it."""
    field = ".".join(str(p) for p in loc[1:]) or "the body"
    ctx = e.get("ctx") or {}
    kind = e.get("type", "")
    bounds = {
        "greater_than": ("greater than", "gt"),
        "greater_than_equal": ("at least", "ge"),
        "less_than": ("less than", "lt"),
        "less_than_equal": ("at most", "le"),
    }
    if kind in bounds:
        words, key = bounds[kind]
        bound = ctx.get(key)
        return f"{field} must be {words} {bound:g}" if isinstance(bound, float) else f"{field} must be {words} {bound}"
    if kind in ("too_long", "string_too_long"):
        return f"{field} is too long: at most {ctx.get('max_length')}"
    if kind in ("too_short", "string_too_short"):
        return f"{field} is too short: at least {ctx.get('min_length')}"
    fixed = {
        "missing": f"{field} is required",
        "extra_forbidden": f"{field} is not a field of this request",
        "float_parsing": f"{field} must be a number",
        "float_type": f"{field} must be a number",
        "int_parsing": f"{field} must be a whole number",
        "int_type": f"{field} must be a whole number",
        "int_from_float": f"{field} must be a whole number",
        "bool_parsing": f"{field} must be true or false",
        "bool_type": f"{field} must be true or false",
        "finite_number": f"{field} must be a finite number",
        "string_type": f"{field} must be text",
        "list_type": f"{field} must be a list",
        "dict_type": f"{field} must be an object",
        "model_type": f"{field} must be an object",
        "model_attributes_type": f"{field} must be an object",
        "union_tag_not_found": f"{field} is required",
    }
    if kind in fixed:
        return fixed[kind]
    if kind in ("literal_error", "enum"):
        return f"{field} must be one of {ctx.get('expected')}"
    if kind.startswith(("datetime_", "date_")):
        return f"{field} must be a date and time in ISO 8601, e.g. 2026-11-27T22:00:00+01:00"
    # a kind not listed: the library's "Input should be ..." said as ours; our own validators' messages without
    # pydantic's prefix; each after the field it is about if it does not say it
    msg = str(e.get("msg", "")).removeprefix("Value error, ")
    if msg.startswith("Input should "):
        return f"{field} " + msg.replace("Input should ", "must ", 1)
    leaf = str(loc[-1]) if len(loc) > 1 else field
    return msg if field in msg or leaf in msg else f"{field}: {msg}"
