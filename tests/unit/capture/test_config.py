"""Config: defaults, profiles, files, environment, overrides, and errors naming file, key and form."""

from __future__ import annotations

import pytest

from capture.app.config import load_config
from capture.errors import ConfigError


def test_defaults_and_precedence(tmp_path):
    s = load_config(env={})
    assert s.recorder.max_loss_s == 1.0 and s.bus.live_queue == 8192 and s.devices == []
    f = tmp_path / "c.toml"
    f.write_text("[recorder]\nmax_loss_s = 0.5\nfsync = false\n[bus]\nlive_queue = 100\n")
    s = load_config(f, profile="ci", env={"PERFCAP_BUS_LIVE_QUEUE": "77"},
                    overrides={"recorder": {"max_loss_s": 0.25}})
    assert s.recorder.max_loss_s == 0.25      # override beats file
    assert s.bus.live_queue == 77              # environment beats file
    assert s.recorder.fsync is False           # file beats profile/default
    assert s.bus.recorder_max_mb == 256        # profile beats default
    assert len(s.devices) == 2                 # from the ci profile


def test_device_tables_and_strings(tmp_path):
    f = tmp_path / "d.toml"
    f.write_text('[[devices]]\nname = "wrist"\nurl = "synth://imu"\noptions = { rate = 50, seed = 2 }\n'
                 '[[devices]]\nkind = "witmotion"\nurl = "synth://imu?seed=3"\n')
    s = load_config(f, env={})
    assert [d.name for d in s.devices] == ["wrist", None]
    assert s.devices[0].options == {"rate": 50, "seed": 2} and s.devices[1].kind == "witmotion"


@pytest.mark.parametrize("text,match", [
    ("[bus]\nlive_queue = 'x'\n", "bus.live_queue = 'x' must be an integer"),
    ("[bus]\nlive_queue = 0\n", "must be within"),
    ("[recorder]\nmax_loss = 1\n", "unknown key recorder.max_loss; \\[recorder\\] takes: max_loss_s"),
    ("[nope]\n", "unknown section or key 'nope'"),
    ("[bus\n", "not valid TOML"),
    ("bus = 3\n", "\\[bus\\] must be a table"),
    ("[recorder]\nfsync = 'yes'\n", "must be true or false"),
    ("devices = 'synth://imu'\n", "devices must be a list"),
    ("devices = ['imu']\n", "devices\\[0\\].*expected \\[NAME=\\]\\[KIND@\\]SCHEME://"),
    ("[[devices]]\nname = 'x'\n", "url = .* is required"),
    ("[[devices]]\nurl = 'synth://imu'\ncolour = 'red'\n", "unknown key 'colour'"),
    ("[[devices]]\nurl = 'synth://imu'\noptions = 3\n", "options must be a table"),
])
def test_errors_name_file_key_and_form(tmp_path, text, match):
    f = tmp_path / "bad.toml"
    f.write_text(text)
    with pytest.raises(ConfigError, match=match) as ei:
        load_config(f, env={})
    assert str(f) in str(ei.value)


def test_unreadable_files_and_profiles(tmp_path):
    with pytest.raises(ConfigError, match="no such config file"):
        load_config(tmp_path / "missing.toml", env={})
    with pytest.raises(ConfigError, match="is a directory"):
        load_config(tmp_path, env={})
    (tmp_path / "bin.toml").write_bytes(b"\xff\xfe\x00garbage")
    with pytest.raises(ConfigError, match="not valid TOML"):
        load_config(tmp_path / "bin.toml", env={})
    with pytest.raises(ConfigError, match="unknown profile 'x'; available: ci, default, lab"):
        load_config(profile="x", env={})


def test_environment_errors():
    with pytest.raises(ConfigError, match="PERFCAP_RECORDER_MAX_LOSS_S"):
        load_config(env={"PERFCAP_RECORDER_MAX_LOSS_S": "soon"})
    with pytest.raises(ConfigError, match="PERFCAP_BUS_SIZE is not a setting"):
        load_config(env={"PERFCAP_BUS_SIZE": "1"})
    assert load_config(env={"PERFCAP_RECORDER_FSYNC": "off"}).recorder.fsync is False


def test_default_toml_documents_exactly_the_built_in_defaults():
    """config/default.toml and the settings' one definition cannot drift apart: same sections, same
    keys, same values."""
    import tomllib
    from dataclasses import fields as dc_fields

    from capture.app.config import PROFILE_DIR, SECTIONS, Settings
    from capture.app.schema import setting_fields

    doc = tomllib.loads((PROFILE_DIR / "default.toml").read_text(encoding="utf-8"))
    built_in = Settings()
    assert set(doc) == set(SECTIONS)
    for name, cls in SECTIONS.items():
        keys = [f.name for f, _ in setting_fields(cls)]
        assert list(doc[name]) == keys, name
        for key in keys:
            assert doc[name][key] == getattr(getattr(built_in, name), key), f"{name}.{key}"
        assert {f.name for f in dc_fields(cls)} >= set(keys)


def test_every_serve_setting_is_a_flag_and_a_key():
    """The flags of perfcap serve are derived from the same definition as the [serve] keys."""
    from capture.app.cli import build_parser
    from capture.app.schema import flag_name, setting_fields
    from capture.app.serve.config import ServeConfig

    serve = build_parser()._subparsers._group_actions[0].choices["serve"]   # the subparser of perfcap serve
    flags = {s for a in serve._actions for s in a.option_strings}
    for f, opt in setting_fields(ServeConfig):
        assert flag_name(f, opt) in flags, f.name
    s = load_config(overrides={"serve": {"osc_port": 9000, "osc_allow": "127.0.0.1", "tls": False}}, env={})
    assert (s.serve.osc_port, s.serve.tls) == (9000, False)
    assert load_config(env={"PERFCAP_SERVE_MAX_PUSH_MB": "8"}).serve.client_limits().max_push_bytes == 8 << 20


def test_the_default_limits_are_the_default_settings_limits():
    """A service built in code with Limits() bounds its clients as one built from the default settings."""
    from capture.app.serve.config import Limits, ServeConfig

    assert ServeConfig().client_limits() == Limits()
