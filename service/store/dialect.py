"""Where the SQL of the two engines differs, in one place. Storage writes its SQL once, with `?`
placeholders and these few expressions; the PostgreSQL engine turns `?` into psycopg's `%s`."""

from __future__ import annotations

import functools
from dataclasses import dataclass


@dataclass(frozen=True)
class Dialect:
    name: str
    # appended to a SELECT that claims rows other workers must skip ("" where the engine has one writer)
    skip_locked: str
    json_text_form: str  # {column}, {key}: a JSON key's value as SQL text, NULL where absent or null
    json_set_form: str  # {column}, {key}: the column's JSON with the key set to the text parameter `?`
    # the database's own clock (one clock for a lab: a bench PC's may be off), as UTC ISO 8601 text in
    # the form of storage.now_iso(), so it compares as text with the timestamps Python writes
    now_text: str
    seconds_since_form: str  # {column}: seconds from the column's UTC ISO time to the database's clock

    def seconds_since(self, column: str) -> str:
        return self.seconds_since_form.format(column=column)

    def json_text(self, column: str, key: str) -> str:
        return self.json_text_form.format(column=column, key=key)

    def json_set_text(self, column: str, key: str) -> str:
        return self.json_set_form.format(column=column, key=key)


SQLITE = Dialect(
    name="sqlite",
    skip_locked="",
    json_text_form="json_extract({column}, '$.{key}')",
    json_set_form="json_set({column}, '$.{key}', ?)",
    # SQLite's 'now' is its host's clock: the one clock of the services sharing a file (all on that host)
    now_text="strftime('%Y-%m-%dT%H:%M:%f+00:00', 'now')",
    seconds_since_form="((julianday('now') - julianday({column})) * 86400.0)",
)

POSTGRESQL = Dialect(
    name="postgresql",
    skip_locked=" FOR UPDATE SKIP LOCKED",
    json_text_form="({column}::jsonb ->> '{key}')",
    json_set_form="jsonb_set({column}::jsonb, '{{{key}}}', to_jsonb(?::text))::text",
    # the server's clock (statement_timestamp: one instant for the whole statement)
    now_text="to_char(statement_timestamp() AT TIME ZONE 'UTC', 'YYYY-MM-DD\"T\"HH24:MI:SS.MS\"+00:00\"')",
    seconds_since_form="(EXTRACT(EPOCH FROM statement_timestamp() - ({column})::timestamptz)::float8)",
)


@functools.lru_cache(maxsize=1024)
def format_placeholders(sql: str) -> str:
    """`?` -> `%s` outside string literals and quoted names, and a literal `%` doubled (psycopg reads
    `%` as the start of a placeholder everywhere)."""
    out = []
    quote = None
    for ch in sql:
        if quote is not None:
            if ch == quote:
                quote = None
        elif ch in ("'", '"'):
            quote = ch
        elif ch == "?":
            out.append("%s")
            continue
        out.append("%%" if ch == "%" else ch)
    return "".join(out)
