"""Where `serve` may listen, and how: loopback as it is; beyond loopback with TLS (server.ssl_certfile
and ssl_keyfile), or in plain HTTP only when told so (server.insecure), with a warning saying what that
exposes. Checked before the database or the bench is touched, so a refusal costs nothing."""

from __future__ import annotations

import ipaddress
import socket
import ssl
from pathlib import Path

from service.cli.startup import StartError
from service.settings import ServerSettings


def check(server: ServerSettings) -> str | None:
    """The warning to print at start (plain HTTP beyond loopback, allowed by --insecure), or None.
    Refuses (StartError: one line, exit 2) plain HTTP beyond loopback without --insecure, and TLS files
    that cannot be used."""
    if server.ssl_keyfile and not server.ssl_certfile:
        raise StartError("--ssl-keyfile was given without --ssl-certfile: TLS needs the certificate too")
    if server.ssl_certfile:
        _check_tls_files(server.ssl_certfile, server.ssl_keyfile)
        return None
    if is_loopback(server.host):
        return None
    where = f"{server.host}:{server.port} ({'every interface' if _is_any(server.host) else 'beyond loopback'})"
    exposed = "bearer tokens, and every request and answer, would cross the network in clear"
    if not server.insecure:
        raise StartError(
            f"--host {server.host} serves plain HTTP on {where}: {exposed}. Give --ssl-certfile and "
            "--ssl-keyfile (README: TLS for a lab), or --insecure (RIPPLECAL_SERVER__INSECURE=true) on a "
            "network you trust"
        )
    return (
        f"ripplecal: warning: plain HTTP on {where} (--insecure): bearer tokens, and every request and answer, cross the "
        "network in clear, readable by anyone on it; use --ssl-certfile/--ssl-keyfile outside a trusted network"
    )


def is_loopback(host: str) -> bool:
    """An address, or a name whose every address, on loopback (127.0.0.0/8, ::1)."""
    try:
        return ipaddress.ip_address(host.strip("[]")).is_loopback
    except ValueError:
        pass
    try:
        addresses = {info[4][0] for info in socket.getaddrinfo(host, None)}
    except (socket.gaierror, UnicodeError):
        return False  # uvicorn will say the name does not resolve
    return bool(addresses) and all(ipaddress.ip_address(str(a).split("%", 1)[0]).is_loopback for a in addresses)


def _is_any(host: str) -> bool:
    try:
        return ipaddress.ip_address(host.strip("[]")).is_unspecified
    except ValueError:
        return False


def _check_tls_files(certfile: str, keyfile: str | None) -> None:
    """Load the certificate and key as the server will: a wrong path or a key that does not match is one
    line at start, not a traceback from the event loop."""
    for what, path in (("--ssl-certfile", certfile), ("--ssl-keyfile", keyfile)):
        if path is not None and not Path(path).is_file():
            raise StartError(f"{what} {path} does not exist or is not a file")
    try:
        ssl.create_default_context(ssl.Purpose.CLIENT_AUTH).load_cert_chain(certfile, keyfile)
    except ssl.SSLError as exc:
        raise StartError(
            f"--ssl-certfile {certfile}"
            + (f" with --ssl-keyfile {keyfile}" if keyfile else "")
            + f" cannot be used for TLS ({exc.reason or exc}): PEM certificate and its private key expected"
        ) from None
    except OSError as exc:
        raise StartError(f"TLS files cannot be read: {exc.strerror or exc} ({exc.filename or certfile})") from None
