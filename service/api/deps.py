"""Annotated dependencies: the service layer and bearer-token roles (viewer < operator < admin), wrong
tokens throttled per client address (service/api/auth_throttle.py)."""

from __future__ import annotations

from typing import Annotated

from fastapi import Depends, HTTPException, Path, Request, status
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer

from service.api.auth_throttle import AuthThrottle
from service.calibration_service import CalibrationService

ROLE_RANK = {"viewer": 0, "operator": 1, "admin": 2}
_bearer = HTTPBearer(auto_error=False)
# where a 401 sends a person: the dashboard's token field, the header for a client, and how a token is made
HOW_TO_GET_A_TOKEN = (
    "enter an operator token in the dashboard's \"API token\" field (in its header) or send 'Authorization: Bearer <token>'; "
    "create one on the service's machine with `ripplecal token create --role operator`"
)


def get_service(request: Request) -> CalibrationService:
    return request.app.state.service


ServiceDep = Annotated[CalibrationService, Depends(get_service)]

# Ids are SQLite INTEGER rowids: a larger path id would overflow SQLite's 64-bit integer (a 500)
ResourceId = Annotated[int, Path(ge=1, le=2**63 - 1, description="id (a positive 64-bit integer)")]


def get_auth_throttle(request: Request) -> AuthThrottle:
    return request.app.state.auth_throttle


def require_role(minimum: str):
    def check(
        request: Request,
        service: ServiceDep,
        throttle: Annotated[AuthThrottle, Depends(get_auth_throttle)],
        credentials: Annotated[HTTPAuthorizationCredentials | None, Depends(_bearer)],
    ) -> str:
        if credentials is None or credentials.scheme.lower() != "bearer":
            raise HTTPException(
                status.HTTP_401_UNAUTHORIZED,
                f"a bearer token is required for this route: {HOW_TO_GET_A_TOKEN}",
                headers={"WWW-Authenticate": "Bearer"},
            )
        client = request.client.host if request.client else "unknown"
        retry_after_s = throttle.retry_after_s(client)
        if retry_after_s is not None:  # before the token is looked at: a throttled client learns nothing from it
            raise HTTPException(
                status.HTTP_429_TOO_MANY_REQUESTS,
                f"too many unknown or revoked tokens from {client}: try again in {retry_after_s} s "
                f"(at most {throttle.max_failures} wrong tokens per {throttle.window_s:g} s)",
                headers={"Retry-After": str(retry_after_s)},
            )
        role = service.records.token_role(credentials.credentials)
        if role is None:
            throttle.failed(client)
            raise HTTPException(
                status.HTTP_401_UNAUTHORIZED,
                f"token unknown or revoked: {HOW_TO_GET_A_TOKEN}",
                headers={"WWW-Authenticate": "Bearer"},
            )
        if ROLE_RANK[role] < ROLE_RANK[minimum]:
            raise HTTPException(status.HTTP_403_FORBIDDEN, f"role {role} may not do this; {minimum} or higher needed")
        return role

    return check


OperatorDep = Annotated[str, Depends(require_role("operator"))]
