"""Settings from TOML files, profiles, ``PERFCAP_*`` environment variables and explicit overrides.

Precedence, strongest first: explicit overrides (CLI flags), environment variables
(``PERFCAP_<SECTION>_<KEY>``, e.g. ``PERFCAP_RECORDER_MAX_LOSS_S=0.5``), the ``--config`` file, the
profile (``config/<profile>.toml`` in the source tree), then the defaults below. Every key is
checked: an unknown section or key, or a value of the wrong type, is a ``ConfigError`` naming the
file, the key and the expected form. So is a ``PERFCAP_*`` variable that names no setting (naming the
one it resembles: a misspelt variable would otherwise be a setting silently not applied), and a file
that is no regular file, larger than 1 MiB, or nested or dotted too deeply to parse in bounded time.

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

    [serve]                    # perfcap serve; every key is also a flag (--osc-port ...): capture.app.serve.config
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

import difflib
import os
import re
import stat
import tomllib
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from capture.app.schema import parse_value, setting, setting_fields
from capture.app.serve.config import ServeConfig
from capture.errors import ConfigError
from devices.options import shown

if TYPE_CHECKING:
    from devices import DeviceSpec, ReconnectPolicy

PROFILE_DIR = Path(__file__).resolve().parents[2] / "config"
#: the largest config file read (a rig's file is a few KiB; a larger one is a mistake, not a config)
MAX_CONFIG_BYTES = 1 << 20
#: ``PERFCAP_*`` variables that are not settings, and what reads them
OTHER_VARIABLES = {"PERFCAP_SIM_TOKEN": "the pairing token of perfcap sim phone"}
#: a key of more parts than this (``a.b.c...``): tomllib's time grows with the square of the parts
MAX_KEY_PARTS = 64
_LONG_KEY_RE = re.compile(r"""(?:^|[{,\[])[ \t]*(?:(?:[\w-]+|"[^"\n]*"|'[^'\n]*')[ \t]*\.[ \t]*){"""
                          + str(MAX_KEY_PARTS) + "}", re.MULTILINE)   # where keys start: a line, [, { or ,
_PROFILE_RE = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_\-]{0,63}$")


@dataclass
class BusSettings:
    live_queue: int = setting(8192, "items a live subscriber may have waiting", min=1, max=10_000_000)
    recorder_max_mb: int = setting(1024, "memory bound of the recorder's queue (MiB)", min=1, max=1_000_000)


@dataclass
class RecorderSettings:
    max_loss_s: float = setting(1.0, "at most this much data lost if the recorder is killed", min=0.01, max=3600)
    fsync: bool = setting(True, "also survive power loss, not only a killed process")
    overwrite: bool = setting(False, "replace an existing session file")
    views: bool = setting(True, "also record every sample and event as messages viewers show with no perfcap code"
                                " (Foxglove: /view, /tf, /log); about twice the raw bytes more on disk")


@dataclass
class ReconnectSettings:
    enabled: bool = setting(True, "retry an unplugged device")
    initial_s: float = setting(0.2, "first retry after an unplug; doubles up to max_s", min=0.001, max=3600)
    max_s: float = setting(5.0, "longest wait between retries", min=0.001, max=3600)
    give_up_after_s: float = setting(0.0, "0 = keep trying until the take ends", min=0, max=10**9)


@dataclass
class OrientationSettings:
    enabled: bool = setting(False, "run orientation fusion on every IMU stream while recording or replaying")
    filter: str = setting("fusion", "the orientation filter", choices=("fusion", "madgwick", "mahony", "ekf"))
    auto_bias: bool = setting(True, "learn the gyro bias from stillness while running")


@dataclass
class CalibrationSettings:
    dir: str = setting("", "where calibrations are kept (default $XDG_DATA_HOME/perfcap/calibration)")


@dataclass
class Settings:
    bus: BusSettings = field(default_factory=BusSettings)
    recorder: RecorderSettings = field(default_factory=RecorderSettings)
    reconnect: ReconnectSettings = field(default_factory=ReconnectSettings)
    orientation: OrientationSettings = field(default_factory=OrientationSettings)
    calibration: CalibrationSettings = field(default_factory=CalibrationSettings)
    serve: ServeConfig = field(default_factory=ServeConfig)
    devices: list[DeviceSpec] = field(default_factory=list)
    sources: list[str] = field(default_factory=list)

    def reconnect_policy(self) -> ReconnectPolicy:
        from devices import ReconnectPolicy

        r = self.reconnect
        return ReconnectPolicy(r.enabled, r.initial_s, r.max_s, 2.0, r.give_up_after_s or None)


#: the sections of a config file, each a settings dataclass (``capture.app.schema``)
SECTIONS: dict[str, type] = {"bus": BusSettings, "recorder": RecorderSettings, "reconnect": ReconnectSettings,
                             "orientation": OrientationSettings, "calibration": CalibrationSettings,
                             "serve": ServeConfig}


def _keys(section: str) -> list[str]:
    return [f.name for f, _ in setting_fields(SECTIONS[section])]


def _apply_section(where: str, name: str, target: Any, data: Any, from_text: bool = False) -> None:
    if not isinstance(data, Mapping):
        raise ConfigError(f"{where}: [{name}] must be a table of keys", source=where)
    options = {f.name: opt for f, opt in setting_fields(type(target))}
    for k, v in data.items():
        if k not in options:
            raise ConfigError(f"{where}: unknown key {name}.{k}; [{name}] takes: {', '.join(options)}", source=where)
        setattr(target, k, parse_value(options[k], f"{name}.{k}", v, where, from_text=from_text))


def _devices(where: str, data: Any) -> list[DeviceSpec]:
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
            raise ConfigError(f"{at}: unknown key {sorted(unknown)[0]!r}; a device table takes url, kind, name,"
                              " options", source=where)
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
        with open(path, "rb", opener=_open_nonblocking) as f:
            st = os.fstat(f.fileno())
            if stat.S_ISDIR(st.st_mode):
                raise IsADirectoryError
            if not stat.S_ISREG(st.st_mode):
                raise ConfigError(f"{where}: not a regular file (a FIFO or a device), not a config file",
                                  source=where)
            raw = f.read(MAX_CONFIG_BYTES + 1)
        if len(raw) > MAX_CONFIG_BYTES:
            raise ConfigError(f"{where}: larger than {MAX_CONFIG_BYTES >> 20} MiB, not a config file", source=where)
        text = raw.decode("utf-8")
        if _LONG_KEY_RE.search(text):
            raise ConfigError(f"{where}: not a config file: a key of more than {MAX_KEY_PARTS} dotted parts",
                              source=where)
        data = tomllib.loads(text)
    except ConfigError:
        raise
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
    except RecursionError:   # tomllib recurses per nesting level of arrays and inline tables
        raise ConfigError(f"{where}: not a config file: its values are nested too deeply", source=where) from None
    except ValueError as exc:  # tomllib's own limits, e.g. an integer of more than 4300 digits
        raise ConfigError(f"{where}: not valid TOML: {exc}", source=where) from None
    for k, v in data.items():
        if k in SECTIONS:
            _apply_section(where, k, getattr(settings, k), v)
        elif k == "devices":
            settings.devices = _devices(where, v)
        else:
            raise ConfigError(f"{where}: unknown section or key {k!r}; expected: {', '.join([*SECTIONS, 'devices'])}",
                              source=where)
    settings.sources.append(where)


def _open_nonblocking(path: str, flags: int) -> int:
    """Open without waiting for a writer, should ``path`` be a FIFO (it is then refused, not read)."""
    return os.open(path, flags | os.O_NONBLOCK)


def _check_environment(env: Mapping[str, str]) -> None:
    """Every ``PERFCAP_*`` variable names a setting (or one of :data:`OTHER_VARIABLES`) and holds text.
    A misspelt variable is an error rather than a setting silently not applied, as an unknown key of a
    config file is.

    Raises:
        ConfigError: naming the variable and, for a misspelling, the variable meant.
    """
    known = [f"PERFCAP_{sec.upper()}_{k.upper()}" for sec in SECTIONS for k in _keys(sec)] + list(OTHER_VARIABLES)
    for k, v in env.items():
        if not k.startswith("PERFCAP_"):
            continue
        try:
            v.encode("utf-8")
        except UnicodeEncodeError:
            raise ConfigError(f"environment: {k} is not UTF-8 text", source=k) from None
        if k in known:
            continue
        close = difflib.get_close_matches(k, known, n=1, cutoff=0.75)
        sec = k[len("PERFCAP_"):].lower().partition("_")[0]
        hint = (f"did you mean {close[0]}?" if close else
                f"[{sec}] takes: {', '.join(_keys(sec))}" if sec in SECTIONS else
                f"the settings are PERFCAP_<SECTION>_<KEY> with a section of {', '.join(SECTIONS)}")
        raise ConfigError(f"environment: {k} is not a setting; {hint}", source=k)


def load_config(path: str | os.PathLike[str] | None = None, profile: str | None = None,
                overrides: Mapping[str, Mapping[str, Any]] | None = None,
                env: Mapping[str, str] | None = None) -> Settings:
    """Settings from defaults, a profile, a file, the environment and overrides (see module docstring).

    Raises:
        ConfigError: unreadable file, bad TOML, unknown key or wrong type.
    """
    s = Settings()
    env = os.environ if env is None else env
    _check_environment(env)
    if profile:
        p = PROFILE_DIR / f"{profile}.toml"
        if not _PROFILE_RE.match(profile) or not p.is_file():
            have = sorted(x.stem for x in PROFILE_DIR.glob("*.toml")) if PROFILE_DIR.is_dir() else []
            raise ConfigError(f"unknown profile {shown(profile)}; available: {', '.join(have) or 'none'}",
                              source=profile)
        _load_file(p, s)
    if path is not None:
        _load_file(Path(path), s)
    for k, v in env.items():
        if not k.startswith("PERFCAP_"):
            continue
        rest = k[len("PERFCAP_"):].lower()
        sec, _, key = rest.partition("_")
        if sec in SECTIONS:
            _apply_section(f"environment {k}", sec, getattr(s, sec), {key: v}, from_text=True)
    for sec, vals in (overrides or {}).items():
        if sec not in SECTIONS:
            raise ValueError(f"unknown settings section {sec!r}")
        _apply_section("command line", sec, getattr(s, sec), {k: v for k, v in vals.items() if v is not None})
    return s
