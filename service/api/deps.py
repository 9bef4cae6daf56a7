"""Annotated dependencies: the service layer and bearer-token roles (viewer < operator < admin)."""

from __future__ import annotations

from typing import Annotated

from fastapi import Depends, HTTPException, Path, Request, status
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer

from service.calibration_service import CalibrationService

ROLE_RANK = {"viewer": 0, "operator": 1, "admin": 2}
_bearer = HTTPBearer(auto_error=False)


def get_service(request: Request) -> CalibrationService:
    return request.app.state.service


ServiceDep = Annotated[CalibrationService, Depends(get_service)]

# Ids are SQLite INTEGER rowids: a larger path id would overflow SQLite's 64-bit integer (a 500)
ResourceId = Annotated[int, Path(ge=1, le=2**63 - 1, description="id (a positive 64-bit integer)")]


def require_role(minimum: str):
    def check(
        service: ServiceDep, credentials: Annotated[HTTPAuthorizationCredentials | None, Depends(_bearer)]
    ) -> str:
        if credentials is None or credentials.scheme.lower() != "bearer":
            raise HTTPException(
                status.HTTP_401_UNAUTHORIZED,
                "a bearer token is required for this route",
                headers={"WWW-Authenticate": "Bearer"},
            )
        role = service.token_role(credentials.credentials)
        if role is None:
            raise HTTPException(
                status.HTTP_401_UNAUTHORIZED, "token unknown or revoked", headers={"WWW-Authenticate": "Bearer"}
            )
        if ROLE_RANK[role] < ROLE_RANK[minimum]:
            raise HTTPException(status.HTTP_403_FORBIDDEN, f"role {role} may not do this; {minimum} or higher needed")
        return role

    return check


OperatorDep = Annotated[str, Depends(require_role("operator"))]
