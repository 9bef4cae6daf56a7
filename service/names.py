"""What a name may be: the bench and schedule names a person types (settings, the command line, the
API) and every service of a lab reads back from one database. One definition for all of them.

A name is printable text: no control characters (a NUL is refused by PostgreSQL's TEXT, a newline makes
`bench-a\\n` a second bench nobody serves), no invisible format characters, no line separators, and no
whitespace at either end (`bench-a ` would look like `bench-a` everywhere it is shown)."""

from __future__ import annotations

import unicodedata

MAX_NAME_LENGTH = 100

# Unicode general categories a name never holds, and how the refusal calls them
_REFUSED_CATEGORIES = {
    "Cc": "a control character",
    "Cf": "an invisible format character",
    "Cs": "a lone surrogate (not text)",
    "Zl": "a line separator",
    "Zp": "a paragraph separator",
}


def check_name(value: str, what: str = "name") -> str:
    """`value` if it is a valid name, else ValueError saying what is wrong with it and how to mend it;
    `what` names it in the message ("bench name", "schedule name")."""
    if not isinstance(value, str):
        raise ValueError(f"{what} must be text, got {type(value).__name__}")
    shown = repr(value[:60]) + ("..." if len(value) > 60 else "")
    if not value:
        raise ValueError(f"{what} is empty: give it a name of 1 to {MAX_NAME_LENGTH} printable characters")
    if len(value) > MAX_NAME_LENGTH:
        raise ValueError(f"{what} {shown} has {len(value)} characters: at most {MAX_NAME_LENGTH}")
    for position, ch in enumerate(value):
        kind = _REFUSED_CATEGORIES.get(unicodedata.category(ch))
        if kind is not None:
            raise ValueError(
                f"{what} {shown} holds {kind} (U+{ord(ch):04X}) at position {position}: a name is printable "
                "text; remove it"
            )
    if value != value.strip():
        raise ValueError(f"{what} {shown} begins or ends with whitespace: remove it (inner spaces are fine)")
    return value
