"""Where per-device IMU calibrations live between takes: one JSON file per device identity.

A calibration belongs to the physical sensor, so the key is the USB serial number when the
transport knows it (``witmotion-1a86-7523-A50285BI``) and otherwise the device's kind and name
(``witmotion-wrist``): the same device string finds the same calibration after a replug or a
restart. ``perfcap calibrate`` writes here; ``perfcap record`` and the orientation processor read
from here, and every session keeps a copy of the calibrations it used, so a replay re-applies
exactly those (not whatever is in the store by then).

Files are written atomically (temporary file, then rename); a damaged file is a ``ConfigError``
naming it, never a silent identity calibration. A stored document (a file here, or a copy in a
session) is read only when it is at most ``MAX_DOCUMENT_BYTES`` long and nests at most
``MAX_DOCUMENT_DEPTH`` deep (a real one is about 2 KB and 4 levels), and a file only when it is a
regular file, so a hostile one costs neither memory nor time.
"""

from __future__ import annotations

import json
import logging
import os
import re
from pathlib import Path
from typing import TYPE_CHECKING, Any

from capture.bounded_io import InputLimitError, json_loads_bounded, read_bounded
from capture.calibration import ImuCalibration
from capture.clock import MONOTONIC, Clock
from capture.errors import ConfigError

if TYPE_CHECKING:
    from collections.abc import Mapping

    from capture.sample import DeviceIdentity

log = logging.getLogger(__name__)

FORMAT = "perfcap.calibration.v1"
MAX_DOCUMENT_BYTES = 1 << 20
MAX_DOCUMENT_DEPTH = 32
_SAFE = re.compile(r"[^A-Za-z0-9._-]+")


def default_dir(env: Mapping[str, str] | None = None) -> Path:
    """``$XDG_DATA_HOME/perfcap/calibration`` (``~/.local/share/...`` when unset)."""
    env = os.environ if env is None else env
    base = env.get("XDG_DATA_HOME") or os.path.join(os.path.expanduser("~"), ".local", "share")
    return Path(base) / "perfcap" / "calibration"


def identity_key(identity: DeviceIdentity) -> str:
    """The file name stem of a device's calibration (see the module docstring)."""
    if identity.serial and identity.vid is not None and identity.pid is not None:
        parts = [identity.kind, f"{identity.vid:04x}", f"{identity.pid:04x}", identity.serial]
    elif identity.serial:
        parts = [identity.kind, identity.serial]
    else:
        parts = [identity.kind, identity.name]
    return _SAFE.sub("_", "-".join(parts)).strip("._") or "device"


def identity_dict(identity: DeviceIdentity) -> dict[str, Any]:
    return {"kind": identity.kind, "name": identity.name, "url": identity.url, "serial": identity.serial,
            "vid": identity.vid, "pid": identity.pid, "address": identity.address}


def calibration_document(identity: DeviceIdentity, cal: ImuCalibration, wall_time_s: float | None = None,
                         note: str = "") -> dict[str, Any]:
    """What is stored (and copied into sessions) for one device."""
    return {"format": FORMAT, "key": identity_key(identity), "identity": identity_dict(identity),
            "saved_wall_time_s": wall_time_s, "note": note, "calibration": json.loads(cal.to_json())}


def parse_calibration_document(text: str | bytes, where: str) -> tuple[dict[str, Any], ImuCalibration]:
    """(the document, its calibration) from stored text.

    Raises:
        ConfigError: not a perfcap calibration, or its content is invalid.
    """
    try:
        doc = json_loads_bounded(text, MAX_DOCUMENT_BYTES, MAX_DOCUMENT_DEPTH)
    except InputLimitError as exc:
        raise ConfigError(f"{where}: not read as a perfcap calibration file: {exc}", source=where) from None
    except (ValueError, UnicodeDecodeError) as exc:
        raise ConfigError(f"{where}: not a perfcap calibration file (not JSON: {exc})", source=where) from None
    if not isinstance(doc, dict) or doc.get("format") != FORMAT or "calibration" not in doc:
        raise ConfigError(f"{where}: not a perfcap calibration file (expected format {FORMAT})", source=where)
    try:
        cal = ImuCalibration.from_json(json.dumps(doc["calibration"]))
    except ConfigError as exc:
        raise ConfigError(f"{where}: {exc}", source=where) from None
    return doc, cal


class CalibrationStore:
    """Calibrations by device identity in ``directory`` (default: ``default_dir()``)."""

    def __init__(self, directory: str | os.PathLike[str] | None = None, clock: Clock = MONOTONIC) -> None:
        self.dir = Path(directory) if directory else default_dir()
        self.clock = clock

    def path_for(self, identity: DeviceIdentity) -> Path:
        return self.dir / f"{identity_key(identity)}.json"

    def load(self, identity: DeviceIdentity) -> ImuCalibration | None:
        """The stored calibration of ``identity``, or None when there is none.

        Raises:
            ConfigError: the file exists but is unreadable or damaged.
        """
        p = self.path_for(identity)
        try:
            text = read_bounded(p, MAX_DOCUMENT_BYTES)
        except FileNotFoundError:
            return None
        except InputLimitError as exc:
            raise ConfigError(f"{p}: not read as a calibration: {exc}", source=str(p)) from None
        except OSError as exc:
            raise ConfigError(f"{p}: cannot read the calibration: {exc.strerror or exc}", source=str(p)) from None
        return parse_calibration_document(text, str(p))[1]

    def save(self, identity: DeviceIdentity, cal: ImuCalibration, note: str = "") -> Path:
        """Store ``cal`` for ``identity`` (atomically); returns the file.

        Raises:
            ConfigError: the directory cannot be written.
        """
        p = self.path_for(identity)
        doc = calibration_document(identity, cal, self.clock.wall_time_s(), note)
        tmp = p.with_suffix(".json.tmp")
        try:
            self.dir.mkdir(parents=True, exist_ok=True)
            tmp.write_text(json.dumps(doc, indent=2) + "\n")
            os.replace(tmp, p)
        except OSError as exc:
            raise ConfigError(f"cannot store the calibration in {self.dir}: {exc.strerror or exc}"
                              " (set [calibration] dir or PERFCAP_CALIBRATION_DIR)", source=str(p)) from None
        log.info("calibration of %s stored in %s", identity.name, p)
        return p

    def remove(self, identity: DeviceIdentity) -> bool:
        try:
            self.path_for(identity).unlink()
            return True
        except FileNotFoundError:
            return False

    def entries(self) -> list[tuple[Path, dict[str, Any] | None, str | None]]:
        """Every stored file: (path, document or None, error or None); damaged files are listed, not hidden."""
        out: list[tuple[Path, dict[str, Any] | None, str | None]] = []
        if not self.dir.is_dir():
            return out
        for p in sorted(self.dir.glob("*.json")):
            try:
                doc, _ = parse_calibration_document(read_bounded(p, MAX_DOCUMENT_BYTES), str(p))
                out.append((p, doc, None))
            except (ConfigError, OSError, InputLimitError) as exc:
                out.append((p, None, str(exc)))
        return out


__all__ = ["CalibrationStore", "calibration_document", "default_dir", "identity_key", "parse_calibration_document"]
