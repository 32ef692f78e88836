"""The one-string device specification and the registries: forms, errors that show the expected form."""

from __future__ import annotations

import pytest

from capture.errors import ConfigError, DeviceUnavailableError
from devices import DeviceSpec, known_kinds, open_device, parse_device_spec
from devices.transports import known_schemes, open_transport, split_url


@pytest.mark.parametrize("text,name,kind,url", [
    ("synth://imu", None, None, "synth://imu"),
    ("wrist=synth://imu?rate=100", "wrist", None, "synth://imu?rate=100"),
    ("witmotion@synth://imu", None, "witmotion", "synth://imu"),
    ("w-2=witmotion@replay:///tmp/a b.mcap?device=x", "w-2", "witmotion", "replay:///tmp/a b.mcap?device=x"),
])
def test_forms(text, name, kind, url):
    s = parse_device_spec(text)
    assert (s.name, s.kind, s.url) == (name, kind, url)
    assert str(s) == text


@pytest.mark.parametrize("text", ["", "   ", "imu", "/dev/ttyUSB0", "9x=synth://imu", "Bad Kind@synth://imu",
                                  "a=b@://x", "synth://imu?rate", "synth://imu?rate=1&rate=2"])
def test_invalid_strings_show_the_expected_form(text):
    with pytest.raises(ConfigError) as ei:
        d = parse_device_spec(text)
        open_device(d)
    msg = str(ei.value)
    assert "SCHEME://" in msg or "option" in msg


def test_unknown_option_names_the_known_ones():
    with pytest.raises(ConfigError, match=r"unknown option 'rte'.*rate"):
        open_device("synth://imu?rte=100")


def test_bad_option_value():
    with pytest.raises(ConfigError, match="rate='fast' is not NUMBER"):
        open_device("synth://imu?rate=fast")
    with pytest.raises(ConfigError, match="within"):
        open_device("synth://imu?rate=0")
    with pytest.raises(ConfigError, match="true\\|false"):
        open_device("synth://imu?realtime=maybe")


def test_unknown_kind_and_scheme():
    with pytest.raises(DeviceUnavailableError, match=r"known kinds: .*witmotion"):
        open_device("nokind@synth://imu")
    with pytest.raises(DeviceUnavailableError, match=r"known schemes: .*synth"):
        open_device("witmotion@bogus://x")
    assert "witmotion" in known_kinds() and {"synth", "replay"} <= set(known_schemes())


def test_unknown_synth_device():
    with pytest.raises(ConfigError, match="unknown synthetic device"):
        open_device("synth://toaster")


def test_names_default_and_must_be_unique():
    taken: set[str] = set()
    a = open_device("synth://imu", taken_names=taken)
    b = open_device("synth://imu", taken_names=taken)
    assert (a.name, b.name) == ("witmotion0", "witmotion1")
    with pytest.raises(ConfigError, match="used twice"):
        open_device("witmotion0=synth://imu", taken_names=taken)


def test_options_from_config_tables_route_to_transport_and_device():
    d = open_device(DeviceSpec("synth://imu", None, "x", {"seed": 3, "rate": 50}))
    assert d.transport.opts["seed"] == 3 and d.opts["rate"] == 50.0
    with pytest.raises(ConfigError, match="both in the URL and in options"):
        open_device(DeviceSpec("synth://imu?seed=1", None, "x", {"seed": 3}))


def test_split_url_and_open_transport():
    assert split_url("synth://imu?rate=5") == ("synth", "imu", {"rate": "5"})
    t = open_transport("synth://imu?rate=5")
    assert t.opts["rate"] == 5.0 and t.implied_kind() == "witmotion"
    with pytest.raises(ConfigError):
        split_url("no-scheme")


@pytest.mark.parametrize("target", [("devices.options", "Option"), ("devices.options", "resolve_options"),
                                    ("devices.witmotion", "NoSuchClass"), ("devices.no_such_module", "X")])
def test_a_registry_entry_that_is_not_a_device_class_is_unavailable(monkeypatch, target):
    import devices

    monkeypatch.setitem(devices.DEVICE_TYPES, "broken", target)
    with pytest.raises(DeviceUnavailableError, match="device kind 'broken'"):
        devices.device_class("broken")


@pytest.mark.parametrize("target", [("devices.options", "Option"), ("devices.witmotion", "WitMotionImu"),
                                    ("devices.transports.base", "Nothing")])
def test_a_registry_entry_that_is_not_a_transport_class_is_unavailable(monkeypatch, target):
    import devices.transports as transports

    monkeypatch.setitem(transports.TRANSPORTS, "broken", target)
    with pytest.raises(DeviceUnavailableError, match="broken://"):
        transports.transport_class("broken")


@pytest.mark.parametrize("url,match", [
    ("synth://imu?rate=nan", "not NUMBER"),
    ("synth://imu?latency_ms=inf", "not NUMBER"),
    ("synth://imu?jitter_ms=-inf", "not NUMBER"),
    ("synth://imu?seed=-1", "at least 0"),
    ("synth://[::1", "invalid transport URL"),
])
def test_bad_option_values_and_urls_are_config_errors(url, match):
    with pytest.raises(ConfigError, match=match):
        open_device(url)
