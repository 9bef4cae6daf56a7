"""Where `serve` may listen (service/cli/exposure.py): loopback as it is, beyond it with TLS or an explicit
--insecure that is warned about; TLS files that cannot be used refused at start in one line."""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

import pytest

from service.cli.exposure import check, is_loopback
from service.cli.startup import StartError
from service.settings import ServerSettings


def _server(**fields) -> ServerSettings:
    return ServerSettings(db_path="unused.db", **fields)


@pytest.mark.parametrize("host", ["127.0.0.1", "127.0.0.5", "::1", "[::1]", "localhost"])
def test_loopback_serves_plain_http_without_a_word(host):
    assert is_loopback(host)
    assert check(_server(host=host)) is None


@pytest.mark.parametrize(
    "host,where", [("0.0.0.0", "every interface"), ("::", "every interface"), ("192.0.2.1", "beyond loopback")]
)
def test_plain_http_beyond_loopback_is_refused_naming_what_it_would_expose(host, where):
    with pytest.raises(StartError) as refused:
        check(_server(host=host))
    message = str(refused.value)
    assert where in message and "bearer tokens" in message and "in clear" in message
    assert "--ssl-certfile" in message and "--insecure" in message and "\n" not in message


def test_insecure_is_allowed_with_a_warning_saying_what_it_exposes():
    warning = check(_server(host="0.0.0.0", insecure=True))
    assert warning.startswith("ripplecal: warning: plain HTTP on 0.0.0.0:8000 (every interface)")
    assert "in clear" in warning


def _key_and_cert(tmp: Path, name: str) -> tuple[Path, Path]:
    openssl = shutil.which("openssl")
    if openssl is None:
        pytest.fail("openssl is missing: apt-get install openssl (Debian's) to make the test certificate")
    cert, key = tmp / f"{name}.crt", tmp / f"{name}.key"
    subprocess.run(
        [openssl, "req", "-x509", "-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:P-256", "-nodes", "-days", "1",
         "-subj", "/CN=127.0.0.1", "-keyout", str(key), "-out", str(cert)],
        check=True, capture_output=True, timeout=60,
    )  # fmt: skip
    return cert, key


def test_tls_files_are_checked_at_start(tmp_path):
    cert, key = _key_and_cert(tmp_path, "a")
    _, other_key = _key_and_cert(tmp_path, "b")
    assert check(_server(host="0.0.0.0", ssl_certfile=str(cert), ssl_keyfile=str(key))) is None
    with pytest.raises(StartError, match="cannot be used for TLS"):
        check(_server(ssl_certfile=str(cert), ssl_keyfile=str(other_key)))  # a key of another certificate
    with pytest.raises(StartError, match="does not exist"):
        check(_server(ssl_certfile=str(tmp_path / "missing.crt"), ssl_keyfile=str(key)))
    with pytest.raises(StartError, match="without --ssl-certfile"):
        check(_server(ssl_keyfile=str(key)))
