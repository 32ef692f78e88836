"""Reading files perfcap did not write (CSV imports, trace files, calibration JSON) within bounds.

``read_bounded`` reads a whole file only when it is a regular file no larger than a cap: a FIFO, a
device such as ``/dev/zero`` or a directory is refused before anything is read (opened without
blocking, checked again on the open descriptor), and a file that grows past the cap while it is read
is refused at the cap, so memory never exceeds it. ``bounded_lines`` hands text out line by line and
refuses a line longer than a cap or more lines than a cap (``longest_line`` measures bytes at
once); ``json_loads_bounded`` refuses JSON nested
deeper than a cap (and turns the ``RecursionError`` Python's own parser raises at about 1000 levels
into the same refusal). Each refusal is an ``InputLimitError`` (a ``ValueError``) that says what was too large and
what the cap is; callers turn it into their own error (``ConfigError``, ``TraceError``) with the file
named.
"""

from __future__ import annotations

import json
import os
import stat
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    from collections.abc import Iterator

MiB = 1 << 20


class InputLimitError(ValueError):
    """An input beyond a bound (too large, too long a line, too deep, not a regular file)."""


def _kind(mode: int) -> str:
    for test, name in ((stat.S_ISDIR, "a directory"), (stat.S_ISFIFO, "a FIFO"), (stat.S_ISCHR, "a character device"),
                       (stat.S_ISBLK, "a block device"), (stat.S_ISSOCK, "a socket")):
        if test(mode):
            return name
    return "not a regular file"


def _size(n: int) -> str:
    return f"{n / MiB:.1f} MiB" if n >= MiB else f"{n} bytes"


def read_bounded(path: str | os.PathLike[str], max_bytes: int) -> bytes:
    """The content of the regular file ``path``, at most ``max_bytes`` long.

    Raises:
        OSError: the file cannot be opened or read.
        InputLimitError: it is not a regular file, or it is larger than ``max_bytes``.
    """
    st = os.stat(path)
    if not stat.S_ISREG(st.st_mode):
        raise InputLimitError(f"{os.fspath(path)} is {_kind(st.st_mode)}, not a regular file")
    fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | getattr(os, "O_CLOEXEC", 0))
    try:
        st = os.fstat(fd)  # what was opened, in case the name was swapped for a FIFO meanwhile
        if not stat.S_ISREG(st.st_mode):
            raise InputLimitError(f"{os.fspath(path)} is {_kind(st.st_mode)}, not a regular file")
        if st.st_size > max_bytes:
            raise InputLimitError(f"{os.fspath(path)} is {_size(st.st_size)}; at most {_size(max_bytes)} is read")
        parts: list[bytes] = []
        got = 0
        while got <= max_bytes:
            block = os.read(fd, min(MiB, max_bytes + 1 - got))
            if not block:
                break
            parts.append(block)
            got += len(block)
    finally:
        os.close(fd)
    if got > max_bytes:
        raise InputLimitError(f"{os.fspath(path)} grew past {_size(max_bytes)} while it was read")
    return b"".join(parts)


def bounded_lines(text: str, max_line: int, max_lines: int, what: str) -> Iterator[str]:
    """The lines of ``text`` (their ends kept), refusing one longer than ``max_line`` characters or
    more than ``max_lines`` of them.

    Raises:
        InputLimitError: (while iterating) a line or the line count beyond its cap, by line number.
    """
    start, n, end = 0, 0, len(text)
    while start < end:
        nl = text.find("\n", start, start + max_line + 1)
        stop = nl + 1 if nl >= 0 else min(end, start + max_line + 1)
        if nl < 0 and stop - start > max_line:
            raise InputLimitError(f"{what} line {n + 1} is longer than {max_line} characters")
        n += 1
        if n > max_lines:
            raise InputLimitError(f"{what} has more than {max_lines} lines")
        yield text[start:stop]
        start = stop


def longest_line(data: bytes, sep: int = 0x0A) -> int:
    """The length of the longest line of ``data`` (line ends not counted), in linear time and in
    memory bounded by a 1 MiB window, however many lines there are."""
    buf = np.frombuffer(data, np.uint8)
    longest, line_start = 0, 0
    for w in range(0, len(buf), MiB):
        ends = np.flatnonzero(buf[w:w + MiB] == sep) + w
        if len(ends):
            starts = np.concatenate(([line_start], ends[:-1] + 1))
            longest = max(longest, int((ends - starts).max()))
            line_start = int(ends[-1]) + 1
    return max(longest, len(buf) - line_start)


def read_text_bounded(path: str | os.PathLike[str], max_bytes: int, max_line: int,
                      encoding: str = "utf-8") -> str:
    """``read_bounded``, with no line longer than ``max_line`` bytes, decoded.

    Raises:
        OSError: the file cannot be opened or read.
        InputLimitError: not a regular file, larger than ``max_bytes``, or a line longer than ``max_line``.
        UnicodeDecodeError: not text in ``encoding``.
    """
    raw = read_bounded(path, max_bytes)
    longest = longest_line(raw)
    if longest > max_line:
        raise InputLimitError(f"{os.fspath(path)} has a line of {_size(longest)}; lines of at most"
                              f" {_size(max_line)} are read")
    return raw.decode(encoding)


def json_depth(doc: Any) -> int:
    """How deeply the lists and dicts of a parsed JSON document nest (a scalar is 0 deep)."""
    depth, todo = 0, [(doc, 1)]
    while todo:
        node, d = todo.pop()
        if isinstance(node, dict):
            node = list(node.values())
        if isinstance(node, list):
            depth = max(depth, d)
            todo.extend((x, d + 1) for x in node if isinstance(x, (list, dict)))
    return depth


def json_loads_bounded(data: str | bytes, max_bytes: int, max_depth: int) -> Any:
    """``json.loads`` of text at most ``max_bytes`` long and nested at most ``max_depth`` deep.

    Raises:
        InputLimitError: too long or too deep.
        ValueError: not JSON (``json.JSONDecodeError``, ``UnicodeDecodeError``).
    """
    size = len(data.encode("utf-8", "surrogatepass")) if isinstance(data, str) else len(data)
    if size > max_bytes:
        raise InputLimitError(f"the JSON is {_size(size)}; at most {_size(max_bytes)} is read")
    try:
        doc = json.loads(data)
    except RecursionError:  # the C parser's own bound, about 1000 levels
        raise InputLimitError(f"the JSON nests deeper than Python's parser goes; at most {max_depth} levels"
                              " are read") from None
    depth = json_depth(doc)
    if depth > max_depth:
        raise InputLimitError(f"the JSON nests {depth} levels deep; at most {max_depth} are read")
    return doc


__all__ = ["InputLimitError", "MiB", "bounded_lines", "json_depth", "json_loads_bounded", "longest_line",
           "read_bounded", "read_text_bounded"]
