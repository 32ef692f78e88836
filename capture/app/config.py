"""Settings from TOML files, profiles, ``PERFCAP_*`` environment variables and explicit overrides.

Precedence, strongest first: explicit overrides (CLI flags), environment variables
(``PERFCAP_<SECTION>_<KEY>``, e.g. ``PERFCAP_RECORDER_MAX_LOSS_S=0.5``), the ``--config`` file, the
profile (``config/<profile>.toml`` in the source tree), then the defaults below. Every key is
checked: an unknown section or key, or a value of the wrong type, is a ``ConfigError`` naming the
file, the key and the expected form.

A config file looks like::

    [bus]
    live_queue = 8192          # items a live subscriber may have waiting
    recorder_max_mb = 1024     # memory bound of the recorder's queue

    [recorder]
    max_loss_s = 1.0           # at most this much data lost if the recorder is killed
    fsync = true

    [reconnect]
    enabled = true
    initial_s = 0.2
    max_s = 5.0
    give_up_after_s = 0        # 0 = keep trying

    [orientation]
    enabled = false            # orientation fusion on every IMU stream (also: record --orientation)
    filter = "fusion"          # fusion | madgwick | mahony | ekf
    auto_bias = true           # learn the gyro bias from stillness

    [calibration]
    dir = ""                   # default: $XDG_DATA_HOME/perfcap/calibration

    [serve]                    # perfcap serve; every key is also a flag (--osc-port ...)
    port = 8443
    osc_port = 9000            # 0 = off; OSC and HyperIMU need an allow-list
    osc_allow = "192.168.1.0/24"

    [[devices]]
    name = "wrist"
    kind = "witmotion"
    url = "serial:///dev/ttyUSB0?baud=115200"
    options = { rate = 200 }

``devices`` may also be a list of device strings: ``devices = ["wrist=witmotion@synth://imu"]``.
"""

from __future__ import annotations

import os
import tomllib
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any
from collections.abc import Mapping

from capture.errors import ConfigError

PROFILE_DIR = Path(__file__).resolve().parents[2] / "config"


@dataclass
class BusSettings:
    live_queue: int = 8192
    recorder_max_mb: int = 1024


@dataclass
class RecorderSettings:
    max_loss_s: float = 1.0
    fsync: bool = True
    overwrite: bool = False


@dataclass
class ReconnectSettings:
    enabled: bool = True
    initial_s: float = 0.2
    max_s: float = 5.0
    give_up_after_s: float = 0.0


@dataclass
class OrientationSettings:
    enabled: bool = False    # run orientation fusion on every IMU stream while recording or replaying
    filter: str = "fusion"   # fusion | madgwick | mahony | ekf
    auto_bias: bool = True   # learn the gyro bias from stillness while running


@dataclass
class CalibrationSettings:
    dir: str = ""            # where calibrations are kept; "" = $XDG_DATA_HOME/perfcap/calibration


@dataclass
class ServeSettings:
    """``perfcap serve`` (see ``capture.app.serve.service.ServeConfig``)."""

    host: str = "0.0.0.0"          # address the phone endpoints listen on
    port: int = 8443               # phone page, WebSocket, Sensor Logger push (HTTPS)
    public_host: str = ""          # the address phones use ("" = the detected LAN address)
    tls: bool = True
    control_host: str = "127.0.0.1"
    control_port: int = 8780       # -1 = no control API
    state_dir: str = ""            # token and certificate ("" = $XDG_DATA_HOME/perfcap/serve)
    sessions_dir: str = "."        # where POST /api/record/start puts sessions without a path
    mdns: bool = True
    mdns_interfaces: str = "all"
    connect_sensorserver: bool = False
    sensorserver_types: str = "accelerometer,gyroscope"
    osc_port: int = 0              # 0 = off
    osc_allow: str = ""
    osc_map: str = "zigsim"
    hyperimu_port: int = 0         # UDP; 0 = off
    hyperimu_tcp_port: int = 0
    hyperimu_allow: str = ""
    hyperimu_sensors: str = "accelerometer,gyroscope,magnetometer"
    phone_names: str = ""          # "page/5f2c...=pocket,sensorlogger/abc=belt"
    max_phones: int = 32
    max_message_kb: int = 64
    max_push_mb: int = 4
    max_rate: float = 200.0        # messages per second per client
    max_connections_per_host: int = 4


@dataclass
class Settings:
    bus: BusSettings = field(default_factory=BusSettings)
    recorder: RecorderSettings = field(default_factory=RecorderSettings)
    reconnect: ReconnectSettings = field(default_factory=ReconnectSettings)
    orientation: OrientationSettings = field(default_factory=OrientationSettings)
    calibration: CalibrationSettings = field(default_factory=CalibrationSettings)
    serve: ServeSettings = field(default_factory=ServeSettings)
    devices: list[Any] = field(default_factory=list)  # DeviceSpec
    sources: list[str] = field(default_factory=list)

    def reconnect_policy(self) -> Any:
        from devices import ReconnectPolicy
        r = self.reconnect
        return ReconnectPolicy(r.enabled, r.initial_s, r.max_s, 2.0, r.give_up_after_s or None)


_SECTIONS = {"bus": BusSettings, "recorder": RecorderSettings, "reconnect": ReconnectSettings,
             "orientation": OrientationSettings, "calibration": CalibrationSettings, "serve": ServeSettings}
_CHOICES: dict[str, tuple[str, ...]] = {"orientation.filter": ("fusion", "madgwick", "mahony", "ekf")}
_LIMITS: dict[str, tuple[float, float]] = {
    "bus.live_queue": (1, 10_000_000), "bus.recorder_max_mb": (1, 1_000_000),
    "recorder.max_loss_s": (0.01, 3600), "reconnect.initial_s": (0.001, 3600), "reconnect.max_s": (0.001, 3600),
    "reconnect.give_up_after_s": (0, 10**9),
    "serve.port": (0, 65535), "serve.control_port": (-1, 65535), "serve.osc_port": (0, 65535),
    "serve.hyperimu_port": (0, 65535), "serve.hyperimu_tcp_port": (0, 65535), "serve.max_phones": (1, 10_000),
    "serve.max_message_kb": (1, 1 << 20), "serve.max_push_mb": (1, 1024), "serve.max_rate": (0.1, 1e6),
    "serve.max_connections_per_host": (1, 10_000),
}
_TYPE_NAMES = {int: "an integer", float: "a number", bool: "true or false", str: "a string"}


def _coerce(where: str, key: str, value: Any, typ: type, from_text: bool) -> Any:
    if from_text:
        text = str(value).strip()
        try:
            if typ is bool:
                if text.lower() in ("1", "true", "yes", "on"):
                    return True
                if text.lower() in ("0", "false", "no", "off"):
                    return False
                raise ValueError
            value = typ(text)
        except ValueError:
            raise ConfigError(f"{where}: {key} = {text!r} must be {_TYPE_NAMES[typ]}", source=where) from None
    ok = (isinstance(value, bool) if typ is bool else
          isinstance(value, int) and not isinstance(value, bool) if typ is int else
          isinstance(value, (int, float)) and not isinstance(value, bool) if typ is float else isinstance(value, typ))
    if not ok:
        raise ConfigError(f"{where}: {key} = {value!r} must be {_TYPE_NAMES[typ]}", source=where)
    if typ is float:
        value = float(value)
    choices = _CHOICES.get(key)
    if choices and value not in choices:
        raise ConfigError(f"{where}: {key} = {value!r} must be one of {', '.join(choices)}", source=where)
    lim = _LIMITS.get(key)
    if lim and not (lim[0] <= value <= lim[1]):
        raise ConfigError(f"{where}: {key} = {value!r} must be within [{lim[0]}, {lim[1]}]", source=where)
    return value


def _apply_section(where: str, name: str, target: Any, data: Any, from_text: bool = False) -> None:
    if not isinstance(data, Mapping):
        raise ConfigError(f"{where}: [{name}] must be a table of keys", source=where)
    types = {f.name: f.type for f in fields(target)}
    for k, v in data.items():
        if k not in types:
            raise ConfigError(f"{where}: unknown key {name}.{k}; [{name}] takes: {', '.join(types)}", source=where)
        typ = {"int": int, "float": float, "bool": bool, "str": str}[str(types[k])]
        setattr(target, k, _coerce(where, f"{name}.{k}", v, typ, from_text))


def _devices(where: str, data: Any) -> list[Any]:
    from devices import DeviceSpec, parse_device_spec

    if not isinstance(data, list):
        raise ConfigError(f"{where}: devices must be a list of device strings or [[devices]] tables", source=where)
    out = []
    for i, d in enumerate(data):
        at = f"{where}: devices[{i}]"
        if isinstance(d, str):
            try:
                out.append(parse_device_spec(d))
            except ConfigError as exc:
                raise ConfigError(f"{at}: {exc}", source=where) from None
            continue
        if not isinstance(d, Mapping):
            raise ConfigError(f"{at} must be a device string or a table with url (and kind, name, options)",
                              source=where)
        unknown = set(d) - {"url", "kind", "name", "options"}
        if unknown:
            raise ConfigError(f"{at}: unknown key {sorted(unknown)[0]!r}; a device table takes url, kind, name, options",
                              source=where)
        if "url" not in d or not isinstance(d["url"], str):
            raise ConfigError(f"{at}: url = \"SCHEME://ADDRESS\" is required", source=where)
        for k in ("kind", "name"):
            if k in d and not isinstance(d[k], str):
                raise ConfigError(f"{at}: {k} must be a string", source=where)
        opts = d.get("options", {})
        if not isinstance(opts, Mapping):
            raise ConfigError(f"{at}: options must be a table, e.g. options = {{ rate = 200 }}", source=where)
        text = d["url"]
        if d.get("kind"):
            text = f"{d['kind']}@{text}"
        if d.get("name"):
            text = f"{d['name']}={text}"
        try:
            spec = parse_device_spec(text)
        except ConfigError as exc:
            raise ConfigError(f"{at}: {exc}", source=where) from None
        out.append(DeviceSpec(spec.url, spec.kind, spec.name, dict(opts)))
    return out


def _load_file(path: Path, settings: Settings) -> None:
    where = str(path)
    try:
        with open(path, "rb") as f:
            data = tomllib.load(f)
    except FileNotFoundError:
        raise ConfigError(f"{where}: no such config file", source=where) from None
    except IsADirectoryError:
        raise ConfigError(f"{where}: is a directory, not a config file", source=where) from None
    except OSError as exc:
        raise ConfigError(f"{where}: cannot read: {exc.strerror or exc}", source=where) from None
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{where}: not valid TOML: {exc}", source=where) from None
    except UnicodeDecodeError:
        raise ConfigError(f"{where}: not valid TOML: not UTF-8 text", source=where) from None
    for k, v in data.items():
        if k in _SECTIONS:
            _apply_section(where, k, getattr(settings, k), v)
        elif k == "devices":
            settings.devices = _devices(where, v)
        else:
            raise ConfigError(f"{where}: unknown section or key {k!r}; expected: {', '.join([*_SECTIONS, 'devices'])}",
                              source=where)
    settings.sources.append(where)


def load_config(path: str | os.PathLike[str] | None = None, profile: str | None = None,
                overrides: Mapping[str, Mapping[str, Any]] | None = None,
                env: Mapping[str, str] | None = None) -> Settings:
    """Settings from defaults, a profile, a file, the environment and overrides (see module docstring).

    Raises:
        ConfigError: unreadable file, bad TOML, unknown key or wrong type.
    """
    s = Settings()
    if profile:
        p = PROFILE_DIR / f"{profile}.toml"
        if not p.is_file():
            have = sorted(x.stem for x in PROFILE_DIR.glob("*.toml")) if PROFILE_DIR.is_dir() else []
            raise ConfigError(f"unknown profile {profile!r}; available: {', '.join(have) or 'none'}", source=profile)
        _load_file(p, s)
    if path is not None:
        _load_file(Path(path), s)
    env = os.environ if env is None else env
    for k, v in env.items():
        if not k.startswith("PERFCAP_"):
            continue
        rest = k[len("PERFCAP_"):].lower()
        sec, _, key = rest.partition("_")
        if sec in _SECTIONS:
            if key not in {f.name for f in fields(_SECTIONS[sec])}:
                raise ConfigError(f"environment: {k} is not a setting; [{sec}] takes: "
                                  f"{', '.join(f.name for f in fields(_SECTIONS[sec]))}", source=k)
            _apply_section(f"environment {k}", sec, getattr(s, sec), {key: v}, from_text=True)
    for sec, vals in (overrides or {}).items():
        if sec not in _SECTIONS:
            raise ValueError(f"unknown settings section {sec!r}")
        _apply_section("command line", sec, getattr(s, sec), {k: v for k, v in vals.items() if v is not None})
    return s
