"""Export a session's samples and events as CSV or JSON lines: one file per stream (``wrist__imu.csv``:
sequence number, the three times, then each channel with its unit) and ``_events.<ext>``."""

from __future__ import annotations

import csv
import json
import math
import os
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Literal

from capture.errors import ConfigError
from capture.sample import NO_TIME

if TYPE_CHECKING:
    from capture.session import SessionReader

#: the columns before the channels in every exported stream
TIMING_COLUMNS = ("seq", "t_host_ns", "t_device_ns", "t_bus_ns")


@dataclass
class ExportResult:
    samples: int
    streams: int
    notes: list[str] = field(default_factory=list)


def export_session(reader: SessionReader, folder: str, fmt: Literal["csv", "jsonl"],
                   overwrite: bool = False) -> ExportResult:
    """Write every stream of ``reader`` and its events into ``folder`` (created if need be).

    Raises:
        ConfigError: ``folder`` is a file, an export file exists and ``overwrite`` is not set, or a
            file cannot be written.
    """
    if os.path.exists(folder) and not os.path.isdir(folder):
        raise ConfigError(f"{folder} exists and is not a directory")
    try:
        os.makedirs(folder, exist_ok=True)
    except OSError as exc:
        raise ConfigError(f"cannot create the folder {folder}: {exc.strerror or exc}") from None
    planned = [os.path.join(folder, s.replace("/", "__") + f".{fmt}") for s in reader.streams]
    planned += [os.path.join(folder, f"_events.{fmt}")]
    clash = [p for p in planned if os.path.exists(p)]
    if clash and not overwrite:
        raise ConfigError(f"{clash[0]} already exists (use --overwrite to replace the export)")
    batches = reader.all_samples()
    total = 0
    for name, info in reader.streams.items():
        b = batches[name]
        path = os.path.join(folder, name.replace("/", "__") + f".{fmt}")
        cols = [*TIMING_COLUMNS, *(f"{c}[{u}]" for c, u in zip(info.channels, info.units, strict=True))]
        seq, th, td, tb, vals = (b.seq.tolist(), b.t_host_ns.tolist(), b.t_device_ns.tolist(), b.t_bus_ns.tolist(),
                                 b.values.tolist())
        try:
            with open(path, "w", newline="") as f:
                if fmt == "csv":
                    w = csv.writer(f)
                    w.writerow(cols)
                    for i in range(len(seq)):
                        w.writerow([seq[i], th[i], "" if td[i] == NO_TIME else td[i], tb[i], *map(repr, vals[i])])
                else:
                    for i in range(len(seq)):
                        values = [None if math.isnan(v) else v for v in vals[i]]
                        f.write(json.dumps({"stream": name, "seq": seq[i], "t_host_ns": th[i],
                                            "t_device_ns": None if td[i] == NO_TIME else td[i], "t_bus_ns": tb[i],
                                            "values": dict(zip(info.channels, values, strict=True))}) + "\n")
        except OSError as exc:
            raise ConfigError(f"cannot write {path}: {exc.strerror or exc}") from None
        total += len(seq)
    ev_path = os.path.join(folder, f"_events.{fmt}")
    evs = reader.events()
    try:
        with open(ev_path, "w", newline="") as f:
            if fmt == "csv":
                w = csv.writer(f)
                w.writerow(["t_host_ns", "source", "kind", "detail"])
                for e in evs:
                    w.writerow([e.get("t_host_ns"), e.get("source"), e.get("kind"), e.get("detail")])
            else:
                for e in evs:
                    f.write(json.dumps(e) + "\n")
    except OSError as exc:
        raise ConfigError(f"cannot write {ev_path}: {exc.strerror or exc}") from None
    res = ExportResult(total, len(reader.streams))
    if reader.truncated:
        res.notes.append(f"the session was not closed cleanly ({reader.truncated}); exported what it holds")
    if reader.damaged:
        res.notes.append("damaged parts were skipped: "
                         + ", ".join(f"{n} x {w}" for w, n in sorted(reader.damaged.items())))
    return res
