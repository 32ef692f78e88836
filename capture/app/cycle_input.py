"""What ``perfcap cycle`` extracts from: a perfcap session's stream or a CSV file (perfcap exports,
Sensor Logger, phyphox and hand-made files: BOM, ``,`` ``;`` or tab separators, trailing delimiters,
seconds or epoch-nanosecond time columns), read into times and values; the extraction timed and its
report drawn. A CSV is read only when it is a regular file within ``MAX_CSV_BYTES``, ``MAX_CSV_LINE``
and ``MAX_CSV_COLUMNS``; anything else is a ``ConfigError`` that says which bound it passed."""

from __future__ import annotations

import csv
import io
import itertools
import os
import stat
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING, Any

import numpy as np

from capture.app.export import TIMING_COLUMNS as EXPORT_TIMING_COLUMNS
from capture.bounded_io import InputLimitError, read_text_bounded
from capture.clock import MONOTONIC
from capture.errors import ConfigError
from capture.session import MCAP_MAGIC

if TYPE_CHECKING:
    from collections.abc import Iterator

    from capture.sample import SampleBatch
    from capture.session import SessionReader
    from cycles import Cycle

#: the CSV files read (a 200 Hz IMU export of 20 minutes is about 12 MB; reading one costs about
#: 6 times its size in memory and 0.5 s per MB), their longest line and their widest row
MAX_CSV_BYTES = 16 << 20
MAX_CSV_LINE = 64 << 10
MAX_CSV_COLUMNS = 1024

CSV_TIME_COLUMNS = ("seconds_elapsed", "t", "time_s", "t_s", "time[s]", "time (s)", "time", "timestamp")


@dataclass
class CycleInput:
    """What ``perfcap cycle`` extracts from: times (s), values (n, C) and how to read the columns."""

    source: str                          # the file, and the stream for a session
    t: np.ndarray                        # (n,) seconds (a session's: from the stream's first sample)
    values: np.ndarray                   # (n, C)
    channels: list[str]
    stream: str | None = None
    quaternions: tuple[tuple[int, int, int, int], ...] = ()
    angles: tuple[int, ...] = ()
    angle_unit: str = "rad"
    origin_ns: int | None = None         # a session's: the bus time of t = 0
    dropped: int = 0                     # rows left out (an empty or non-finite value)


def split_columns(spec: str | None) -> list[str] | None:
    if spec is None:
        return None
    names = [c.strip() for c in spec.split(",") if c.strip()]
    if not names:
        raise ConfigError("--columns needs at least one column name (A,B,...)")
    if len(set(names)) != len(names):
        raise ConfigError(f"--columns names a column twice: {spec}")
    return names


def _pick(available: list[str], wanted: list[str], what: str) -> list[int]:
    idx = []
    for name in wanted:
        if name not in available:
            raise ConfigError(f"no column {name!r} in {what}; its columns are: {', '.join(available)}")
        idx.append(available.index(name))
    return idx


def session_cycle_input(reader: SessionReader, stream: str | None, columns: list[str] | None) -> CycleInput:

    path = reader.path
    if stream is not None and stream in reader.streams:
        b = reader.samples(stream)          # only the stream asked for (sessions can be large)
        if len(b.t_bus_ns):
            return _session_stream_input(reader, stream, b, columns)
    batches = {n: reader.samples(n) for n in reader.streams}
    filled = [n for n in reader.streams if len(batches[n].t_bus_ns) > 0]
    listing = ", ".join(f"{n} ({reader.streams[n].kind})" for n in filled) or "none"
    if stream is None:
        if not filled:
            raise ConfigError(f"{path}: the session holds no samples")
        if len(filled) == 1:
            stream = filled[0]
        else:
            for kinds in (("imu",), ("quat", "orientation"), ("euler",)):
                of_kind = [n for n in filled if reader.streams[n].kind in kinds]
                if len(of_kind) == 1:
                    stream = of_kind[0]
                    break
                if of_kind:
                    break
        if stream is None:
            raise ConfigError(f"{path} has {len(filled)} streams; choose one with --stream: {listing}")
    if stream not in reader.streams:
        raise ConfigError(f"{path} has no stream {stream!r}; its streams: {listing}")
    b = batches[stream]
    if len(b.t_bus_ns) == 0:
        raise ConfigError(f"stream {stream} of {path} holds no samples; streams with samples: {listing}")
    return _session_stream_input(reader, stream, b, columns)


def _session_stream_input(reader: SessionReader, stream: str, b: SampleBatch, columns: list[str] | None) -> CycleInput:
    path = reader.path
    info = reader.streams[stream]
    chans = list(info.channels)
    if columns is not None:
        idx = _pick(chans, columns, f"stream {stream}")
    elif info.kind == "imu":  # the temperature is no part of the motion (and drifts on its own)
        idx = [i for i, u in enumerate(info.units) if u != "degC"] or list(range(len(chans)))
    else:
        idx = list(range(len(chans)))
    values = np.asarray(b.values, np.float64)[:, idx]
    names = [chans[i] for i in idx]
    quats: tuple[tuple[int, int, int, int], ...] = ()
    angles: tuple[int, ...] = ()
    unit = "rad"
    if info.kind in ("quat", "orientation") and all(c in names for c in ("w", "x", "y", "z")):
        w, x, y, z = (names.index(c) for c in ("w", "x", "y", "z"))
        quats = ((w, x, y, z),)
    elif info.kind == "euler":
        units = {info.units[i] for i in idx}
        angles = tuple(range(len(idx)))
        unit = "deg" if units <= {"deg"} else "rad"
    origin = int(b.t_bus_ns[0])
    t = (np.asarray(b.t_bus_ns, np.int64) - origin) / 1e9
    keep = np.all(np.isfinite(values), axis=1)
    return CycleInput(f"{path} {stream}", t[keep], values[keep], names, stream=stream, quaternions=quats, angles=angles,
                       angle_unit=unit, origin_ns=origin, dropped=int((~keep).sum()))


def _csv_rows(text: str, dialect: Any, path: str) -> Iterator[list[str]]:
    """The non-blank rows of a CSV text, each at most ``MAX_CSV_COLUMNS`` fields."""
    for fields in csv.reader(io.StringIO(text, newline=""), dialect):
        if len(fields) > MAX_CSV_COLUMNS:
            raise InputLimitError(f"{path} has a row of {len(fields)} fields; at most {MAX_CSV_COLUMNS} are read")
        if fields and any(c.strip() for c in fields):
            yield fields


def _number(x: str) -> float | None:
    try:
        return float(x)
    except ValueError:
        return None


def _trailing_blanks(row: list[str], at_most: int) -> int:
    n = 0
    for c in reversed(row):
        if n >= at_most or c.strip():
            break
        n += 1
    return n


def csv_cycle_input(path: str, columns: list[str] | None) -> CycleInput:
    """Times and values from a CSV file, in two passes over its rows (the first finds the header, the
    row count and the trailing empty columns, the second converts the cells used), so memory is the
    text and one array, not a list of every cell.

    Raises:
        ConfigError: unreadable, beyond the module's bounds, or not such a CSV (the line named).
    """
    try:   # (utf-8-sig: a BOM is not part of the first name)
        text = read_text_bounded(path, MAX_CSV_BYTES, MAX_CSV_LINE, encoding="utf-8-sig")
        try:
            dialect: Any = csv.Sniffer().sniff(text[:8192], delimiters=",;\t")
        except csv.Error:
            dialect = csv.excel
        rows = _csv_rows(text, dialect, path)
        first = next(rows, None)
        if first is None:
            raise ConfigError(f"{path} is empty: expected a CSV with a time column (s) and channel columns")
        header = any(_number(c) is None for c in first if c.strip())
        names = [c.strip() for c in first] if header else [f"c{i}" for i in range(len(first))]
        # a trailing delimiter on every line makes an empty, unnamed column: dropped (as many as every
        # row of the header's length leaves empty)
        n_body, same_length, blanks = 0, True, len(names)
        for row in rows if header else itertools.chain([first], rows):
            n_body += 1
            if len(row) != len(names):
                same_length = False
            elif same_length:
                blanks = min(blanks, _trailing_blanks(row, blanks))
        while same_length and blanks and len(names) > 1 and not names[-1]:
            names.pop()
            blanks -= 1
        width = len(names)
        body = _csv_rows(text, dialect, path)
        if header:
            next(body)
        if len(names) < 2:
            raise ConfigError(f"{path}: expected a time column and at least one channel column, found one column")
        lower = [n.lower() for n in names]
        t_col, t_scale = 0, 1.0
        for cand in CSV_TIME_COLUMNS:
            if cand in lower:
                t_col = lower.index(cand)
                break
        else:
            if "t_bus_ns" in lower:  # a perfcap export
                t_col, t_scale = lower.index("t_bus_ns"), 1e-9
        if columns is not None:
            idx = _pick(names, columns, path)
            if t_col in idx:
                raise ConfigError(f"--columns: {names[t_col]!r} is the time column")
        else:
            # (a perfcap export's timing columns, other clocks (Sensor Logger's epoch ns 'time' beside its
            # 'seconds_elapsed') and an IMU's temperature are no part of the motion)
            idx = [i for i, n in enumerate(lower) if i != t_col and n not in EXPORT_TIMING_COLUMNS
                   and n not in CSV_TIME_COLUMNS and not n.endswith("[degc]")]
            if not idx:
                raise ConfigError(f"{path}: no channel columns besides the time column {names[t_col]!r}")
        data = np.full((n_body, len(idx) + 1), np.nan)
        cols, nan = [t_col, *idx], float("nan")
        for r, row in enumerate(body):
            if same_length:
                row = row[:width]  # noqa: PLW2901 - the dropped trailing columns
            if len(row) != width:
                raise ConfigError(f"{path} line {r + 1 + header}: {len(row)} fields where the header has {width}")
            cells = [row[col].strip() for col in cols]
            try:
                data[r] = [float(c) if c else nan for c in cells]
            except ValueError:
                bad = next(j for j, c in enumerate(cells) if c and _number(c) is None)
                raise ConfigError(f"{path} line {r + 1 + header}, column {names[cols[bad]]!r}: {cells[bad]!r}"
                                  " is not a number") from None
        del text
    except UnicodeDecodeError:
        raise ConfigError(f"{path} is neither a perfcap session nor a text CSV file") from None
    except InputLimitError as exc:
        raise ConfigError(f"{exc} (for a longer take, extract from its perfcap session)") from None
    except (OSError, csv.Error) as exc:
        raise ConfigError(f"cannot read {path}: {getattr(exc, 'strerror', None) or exc}") from None
    keep = np.all(np.isfinite(data), axis=1)
    data = data[keep]
    if not len(data):
        raise ConfigError(f"{path}: no rows with a time and every channel")
    if t_scale == 1.0 and len(data) > 2 and float(np.median(np.diff(data[:, 0]))) >= 1e5:
        t_scale = 1e-9   # steps of more than a day: the time column counts nanoseconds (an epoch clock)
    return CycleInput(path, data[:, 0] * t_scale, data[:, 1:], [names[i] for i in idx],
                       dropped=int((~keep).sum()))


def read_cycle_input(path: str, stream: str | None, columns: list[str] | None) -> CycleInput:
    if not os.path.exists(path):
        raise ConfigError(f"{path}: no such file")
    if os.path.isdir(path):
        raise ConfigError(f"{path} is a directory, not a session or CSV file")
    try:
        if not stat.S_ISREG(os.stat(path).st_mode):  # a FIFO would block the open, /dev/zero never end
            raise ConfigError(f"{path} is not a regular file (a session or a CSV file is)")
        with open(path, "rb") as f:
            magic = f.read(len(MCAP_MAGIC))
    except OSError as exc:
        raise ConfigError(f"cannot read {path}: {exc.strerror or exc}") from None
    if magic == MCAP_MAGIC:
        from capture.session import SessionReader

        return session_cycle_input(SessionReader(path), stream, columns)
    if stream is not None:
        raise ConfigError(f"--stream is for perfcap sessions; {path} is not one (for a CSV, use --columns)")
    return csv_cycle_input(path, columns)


def extract_cycle(inp: CycleInput, seed: int = 0) -> Cycle:
    """``cycles.extract`` on a read input, timed (``elapsed_ms`` is the extraction alone)."""
    from cycles import extract

    t0 = MONOTONIC.now_ns()
    cyc = extract(inp.t, inp.values, channels=inp.channels, quaternions=inp.quaternions, angles=inp.angles,
                  angle_unit=inp.angle_unit, seed=seed)
    return replace(cyc, elapsed_ms=(MONOTONIC.now_ns() - t0) / 1e6)


def write_cycle_report(cyc: Cycle, path: str, title: str) -> None:
    """The report image, with its failures as one-line ``ConfigError`` s."""
    try:
        from cycles.report import write_report
    except ImportError as exc:
        raise ConfigError(f"the report needs matplotlib ({exc}); pip install 'matplotlib>=3.8'") from None
    try:
        write_report(cyc, path, title=title)
    except OSError as exc:
        raise ConfigError(f"cannot write {path}: {exc.strerror or exc}") from None
    except ValueError as exc:
        raise ConfigError(f"cannot write the report {path}: {exc}") from None
