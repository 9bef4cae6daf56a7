"""One definition of a valid name (service/names.py), and the settings' bench_name held to it wherever it
is set: the settings file, the environment, the command line (--bench-name), a bench file's own name."""

from __future__ import annotations

import json

import pytest

from service.names import MAX_NAME_LENGTH, check_name
from service.settings import SettingsError, load_settings
from tests.support.service_process import cli


@pytest.mark.parametrize("name", ["bench-a", "A", "Prüfstand 2", "line 3 / rig #1", "x" * MAX_NAME_LENGTH])
def test_printable_names_are_kept_as_they_are(name):
    assert check_name(name, "bench name") == name


@pytest.mark.parametrize(
    "name, says",
    [
        ("bench\x00a", "a control character (U+0000) at position 5"),
        ("bench-a\n", "a control character (U+000A) at position 7"),
        ("bench\ta", "a control character (U+0009)"),
        ("bench\x1b[31ma", "a control character (U+001B)"),
        ("bench\u200ba", "an invisible format character (U+200B)"),
        ("bench\u202ea", "an invisible format character (U+202E)"),
        ("bench\u2028a", "a line separator (U+2028)"),
        ("bench\ud800a", "a lone surrogate"),
        (" bench-a", "begins or ends with whitespace"),
        ("bench-a ", "begins or ends with whitespace"),
        ("\u00a0bench-a", "begins or ends with whitespace"),
        ("", "is empty"),
        ("x" * (MAX_NAME_LENGTH + 1), f"at most {MAX_NAME_LENGTH}"),
    ],
)
def test_a_name_with_control_characters_or_outer_whitespace_is_refused_saying_what_is_wrong(name, says):
    with pytest.raises(ValueError) as refused:
        check_name(name, "bench name")
    text = str(refused.value)
    assert text.startswith("bench name") and says in text, text
    assert "\x00" not in text and "\n" not in text  # the message itself is one printable line


@pytest.mark.parametrize("name", ["bench-a\n", "a\x00b", " padded"])
def test_the_settings_bench_name_is_held_to_it_from_every_source(name, tmp_path):
    with pytest.raises(SettingsError, match="bench_name: bench name"):
        load_settings(environ={}, overrides={"bench_name": name})
    with pytest.raises(SettingsError, match="RIPPLECAL_BENCH_NAME"):
        load_settings(environ={"RIPPLECAL_BENCH_NAME": json.dumps(name)})  # a TOML string, escapes and all
    toml = tmp_path / "bench.toml"
    toml.write_text(f"bench_name = {json.dumps(name)}\n")
    with pytest.raises(SettingsError, match=f"settings file {toml}: bench_name: bench name"):
        load_settings(toml, environ={})


def test_serve_refuses_a_bench_name_with_a_newline_in_one_line(tmp_path):
    refused = cli("serve", "--bench-name", "bench-a\n", "--db", str(tmp_path / "x.db"), check=False, timeout=120)
    assert refused.returncode == 2, refused.stderr
    line = refused.stderr.strip().splitlines()[-1]
    assert "bench name 'bench-a\\n' holds a control character (U+000A)" in line, line
    assert not (tmp_path / "x.db").exists()  # refused before the database is opened


def test_schedule_add_refuses_a_name_with_a_control_character_as_the_api_does(tmp_path):
    db = str(tmp_path / "x.db")
    refused = cli(
        "schedule",
        "add",
        "--name",
        "nightly\t",
        "--cron",
        "0 3 * * *",
        "--torque",
        "1",
        "--speed",
        "1000",
        "--db",
        db,
        check=False,
        timeout=120,
    )
    assert refused.returncode == 2, refused.stderr
    assert "schedule name 'nightly\\t' holds a control character (U+0009)" in refused.stderr, refused.stderr
