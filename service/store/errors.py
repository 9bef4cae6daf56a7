"""What storage raises, whichever engine is behind it (service/store/engines.py)."""

from __future__ import annotations

from service.errors import Unavailable


class StorageError(RuntimeError):
    pass


class StorageUnavailable(Unavailable, StorageError):
    """The database cannot be used now, for a reason that passes (another process holds its lock, its
    filesystem is read-only or full, an I/O error, its server cannot be reached): what needs it waits and
    tries again; the API answers 503 with Retry-After. str() names the cause and the database (for the
    log); `public` names it without the server's path to it (for answers and a sweep's pause reason)."""

    def __init__(self, cause: str, message: str, retry_after_s: float = 5.0, public: str | None = None):
        super().__init__(message)
        self.cause = cause
        self.retry_after_s = retry_after_s
        self.public = public if public is not None else message
