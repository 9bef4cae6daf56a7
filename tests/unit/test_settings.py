"""Settings: TOML + environment overrides; the README's bench example is valid; bad settings say what is wrong."""

import re
from pathlib import Path

import pytest

from service.settings import SettingsError, load_settings

README = Path(__file__).resolve().parents[2] / "README.md"


def test_readme_bench_example_is_valid(tmp_path):
    block = re.search(r"```toml\n(.*?)```", README.read_text(), re.S).group(1)
    (tmp_path / "bench.toml").write_text(block)
    s = load_settings(tmp_path / "bench.toml", environ={})
    assert s.can.interface == "socketcan" and s.daq.url == "/dev/ttyUSB0" and s.motor.pole_pairs == 4


def test_environment_overrides_file(tmp_path):
    (tmp_path / "s.toml").write_text('[can]\nchannel = "can0"\n')
    s = load_settings(tmp_path / "s.toml", environ={"RIPPLECAL_CAN__CHANNEL": "can1", "RIPPLECAL_SERVER__PORT": "8001"})
    assert s.can.channel == "can1" and s.server.port == 8001


def test_defaults_bind_loopback_and_emulate():
    s = load_settings(environ={})
    assert s.server.host == "127.0.0.1" and s.bench_mode == "emulate" and s.can.host == "127.0.0.1"


@pytest.mark.parametrize(
    "text,needle",
    [
        ("[can]\nchanel = 'can0'\n", "can.chanel"),  # misspelt key
        ("[motor]\npole_pairs = 0\n", "motor.pole_pairs"),  # out of range
        ("[motor\n", "not valid TOML"),
    ],
)
def test_bad_settings_name_the_problem(tmp_path, text, needle):
    (tmp_path / "s.toml").write_text(text)
    with pytest.raises(SettingsError, match=re.escape(needle)):
        load_settings(tmp_path / "s.toml", environ={})


def test_missing_file_is_named(tmp_path):
    with pytest.raises(SettingsError, match="does not exist"):
        load_settings(tmp_path / "nope.toml", environ={})


# --- every problem in one line naming the file (or the variable) and the key ----------------------------
@pytest.mark.parametrize(
    "text,needle",
    [
        ("[daq]\nurll = '/dev/ttyUSB0'\n", "daq.urll: unknown key"),
        ("bench_nam = 'x'\n", "bench_nam: unknown key"),
        ("[safety]\nmin_speed_rpm = 7000\n", "safety: min_speed_rpm 7000 must be below max_speed_rpm 6000"),
        ("[daq\nurl = 1\n", "is not valid TOML: "),
    ],
)
def test_a_bad_file_is_one_line_naming_it_and_the_key(tmp_path, text, needle):
    path = tmp_path / "bench.toml"
    path.write_text(text)
    with pytest.raises(SettingsError) as exc:
        load_settings(path, environ={})
    message = str(exc.value)
    assert message.startswith(f"settings file {path}") and needle in message and "\n" not in message, message


def test_a_bad_environment_variable_is_named(tmp_path):
    (tmp_path / "s.toml").write_text('[can]\nchannel = "can0"\n')
    with pytest.raises(SettingsError) as exc:
        load_settings(tmp_path / "s.toml", environ={"RIPPLECAL_SERVER__PORT": "eighty"})
    assert "server.port" in str(exc.value) and "(set by environment RIPPLECAL_SERVER__PORT)" in str(exc.value)
    with pytest.raises(SettingsError, match=r"\(set by the command line\)"):
        load_settings(environ={}, overrides={"server.port": 0})


@pytest.mark.parametrize(
    "make,needle",
    [
        (lambda p: p.mkdir(), "is a directory"),
        (lambda p: p.write_bytes(b"\xff\xfe[daq]"), "is not UTF-8 text"),
    ],
)
def test_a_file_that_is_no_toml_text_is_named(tmp_path, make, needle):
    path = tmp_path / "bench.toml"
    make(path)
    with pytest.raises(SettingsError, match=re.escape(f"settings file {path} {needle}")):
        load_settings(path, environ={})


def test_a_section_that_is_not_a_table_under_an_environment_override(tmp_path):
    (tmp_path / "s.toml").write_text('can = "can0"\n')
    with pytest.raises(SettingsError, match="can is not a table, so environment RIPPLECAL_CAN__CHANNEL cannot set"):
        load_settings(tmp_path / "s.toml", environ={"RIPPLECAL_CAN__CHANNEL": "can1"})
