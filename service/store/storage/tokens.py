"""The API's tokens (table api_tokens): only their sha256 is stored; a token seen valid stays valid in
this process while the database is unavailable."""

from __future__ import annotations

import hashlib
import secrets
from functools import cached_property
from typing import Any

from service.store.errors import StorageUnavailable
from service.store.storage.database import Database
from service.store.storage.rows import as_record, new_id, now_iso, one_row


class TokenStore(Database):
    @cached_property
    def _known_tokens(self) -> dict[str, str]:
        """sha256 -> role of tokens seen valid (used while the database is unavailable). Made on first use,
        so that Database.__init__ stays the stores' one constructor (3.11's cached_property locks that use)."""
        return {}

    def create_token(self, role: str, label: str = "") -> tuple[int, str]:
        token = "rc_" + secrets.token_urlsafe(32)
        with self.transaction() as conn:
            cur = conn.execute(
                "INSERT INTO api_tokens (role, token_sha256, label, created_at) VALUES (?, ?, ?, ?)",
                (role, _sha256(token), label, now_iso()),
            )
            return new_id(cur), token

    def revoke_token(self, token_id: int) -> bool:
        with self.transaction() as conn:
            cur = conn.execute(
                "UPDATE api_tokens SET revoked_at = ? WHERE id = ? AND revoked_at IS NULL", (now_iso(), token_id)
            )
            return one_row(cur)

    def token_role(self, token: str) -> str | None:
        """The token's role (None: unknown or revoked). While the database is unavailable, a token this
        process has seen valid before stays valid (an operator can still cancel or pause; revoking one
        needs the database anyway)."""
        digest = _sha256(token)
        if digest in self._known_tokens and self.known_unavailable() is not None:
            return self._known_tokens[digest]  # an operator's cancel is not held for the database's timeout
        try:
            with self.connect() as conn:
                row = conn.execute(
                    "SELECT role FROM api_tokens WHERE token_sha256 = ? AND revoked_at IS NULL", (digest,)
                ).fetchone()
        except StorageUnavailable:
            if digest in self._known_tokens:
                return self._known_tokens[digest]
            raise
        role = row["role"] if row else None
        if role is None:
            self._known_tokens.pop(digest, None)
        else:
            self._known_tokens[digest] = role
        return role

    def list_tokens(self) -> list[dict[str, Any]]:
        with self.connect() as conn:
            return [
                as_record(r)
                for r in conn.execute("SELECT id, role, label, created_at, revoked_at FROM api_tokens ORDER BY id")
            ]


def _sha256(token: str) -> str:
    return hashlib.sha256(token.encode()).hexdigest()
