"""Typed options for transports and devices, given as URL query keys or config tables.

Each Transport or Device class declares ``options: dict[str, Option]``; values are coerced and
checked here, and an unknown key or a bad value raises ``ConfigError`` that shows the expected form.
"""

from __future__ import annotations

import argparse
import math
import reprlib
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from capture.errors import ConfigError

if TYPE_CHECKING:
    from collections.abc import Callable, Mapping

_TRUE = {"1", "true", "yes", "on"}
_FALSE = {"0", "false", "no", "off"}


@dataclass(frozen=True)
class Option:
    """One option: its type (``int``, ``float``, ``bool``, ``str``), default, help and allowed choices."""

    type: type
    default: Any
    help: str
    choices: tuple[str, ...] | None = None
    min: float | None = None
    max: float | None = None
    min_exclusive: bool = False   # the value must be above ``min``, not equal to it

    def form(self) -> str:
        if self.choices:
            return "|".join(self.choices)
        return {int: "INT", float: "NUMBER (finite)", bool: "true|false", str: "TEXT"}.get(self.type, "VALUE")

    def parse(self, value: Any) -> Any:
        """``value`` as this option's type, checked against its choices and range: the one value parser of
        device options, transport options and settings.

        Numbers are finite (``nan``, ``inf`` and ``1e999`` are refused); text holds no NUL character and
        nothing that is not Unicode (an undecodable byte, as ``os.fsdecode`` hands it over).

        Raises:
            BadValueError: with ``.problem`` ``"type"``, ``"choice"``, ``"range"`` or ``"text"``.
        """
        try:
            if self.type is bool:
                if isinstance(value, bool):
                    v: Any = value
                elif str(value).lower() in _TRUE:
                    v = True
                elif str(value).lower() in _FALSE:
                    v = False
                else:
                    raise ValueError
            elif self.type is int:
                if isinstance(value, bool) or (isinstance(value, float) and not value.is_integer()):
                    raise ValueError
                v = int(value)
            elif self.type is float:
                if isinstance(value, bool):
                    raise ValueError
                v = float(value)
                if not math.isfinite(v):
                    raise ValueError
            else:
                v = str(value)
        except (TypeError, ValueError, RecursionError):   # RecursionError: str() of a deeply nested value
            raise BadValueError("type") from None
        if isinstance(v, str) and not _is_text(v):
            raise BadValueError("text")
        if self.choices and v not in self.choices:
            raise BadValueError("choice")
        if self.min is not None and (v <= self.min if self.min_exclusive else v < self.min):
            raise BadValueError("range")
        if self.max is not None and v > self.max:
            raise BadValueError("range")
        return v

    def range_text(self) -> str:
        """The bounds in words (``within [1, 5]``, ``at least 0``, ``above 0``); ``any value`` for an option
        without any."""
        if self.min is not None and self.max is not None:
            return f"within {'(' if self.min_exclusive else '['}{self.min:g}, {self.max:g}]"
        if self.min is not None:
            return f"{'above' if self.min_exclusive else 'at least'} {self.min:g}"
        return f"at most {self.max:g}" if self.max is not None else "any value"

    def problem_text(self, problem: str) -> str:
        """What a value with ``problem`` (a ``BadValueError``'s) should have been, as the end of a sentence."""
        return {"type": f"is not {self.form()}", "choice": f"must be one of {self.form()}",
                "range": f"must be {self.range_text()}",
                "text": "must be text without NUL characters or undecodable bytes"}[problem]

    def coerce(self, key: str, value: Any, where: str) -> Any:
        """:meth:`parse`, with a bad value said as a URL or device option (``rate='x' is not NUMBER``).

        Raises:
            ConfigError: naming ``where``, the key and the expected form.
        """
        try:
            return self.parse(value)
        except BadValueError as exc:
            raise ConfigError(f"{where}: option {key}={shown(value)} {self.problem_text(exc.problem)}",
                              source=where) from None


def _is_text(s: str) -> bool:
    if "\x00" in s:
        return False
    try:
        s.encode("utf-8")
    except UnicodeEncodeError:   # lone surrogates: bytes that were not UTF-8
        return False
    return True


_SHOWN = reprlib.Repr()
_SHOWN.maxstring = 60
_SHOWN.maxother = 60
_SHOWN.maxlevel = 3
_SHOWN.maxlist = _SHOWN.maxtuple = _SHOWN.maxdict = 4


def shown(value: Any) -> str:
    """``repr(value)`` cut short, so a message stays one readable line whatever the value (a 5,000-digit
    number, a list nested 900 deep)."""
    return _SHOWN.repr(value)


def arg_type(opt: Option) -> Callable[[str], Any]:
    """An argparse ``type=`` that parses a flag's text with ``opt``, the one value parser: a bad value is
    argparse's one-line usage error (``argument --duration: 'nan' is not NUMBER (finite)``)."""

    def parse(text: str) -> Any:
        try:
            return opt.parse(text.strip())
        except BadValueError as exc:
            raise argparse.ArgumentTypeError(f"{shown(text)} {opt.problem_text(exc.problem)}") from None

    parse.__name__ = opt.form()
    return parse


class BadValueError(ValueError):
    """A value an ``Option`` does not take; ``problem`` is ``"type"``, ``"choice"``, ``"range"`` or ``"text"``."""

    def __init__(self, problem: str) -> None:
        super().__init__(problem)
        self.problem = problem


def resolve_options(spec: Mapping[str, Option], given: Mapping[str, Any], where: str, usage: str) -> dict[str, Any]:
    """Defaults overlaid with ``given``, coerced; unknown keys raise ``ConfigError`` naming the known ones."""
    out = {k: o.default for k, o in spec.items()}
    for k, v in given.items():
        if k not in spec:
            known = ", ".join(f"{n}={o.form()}" for n, o in spec.items()) or "none"
            raise ConfigError(f"{where}: unknown option {k!r}; expected {usage} with options: {known}", source=where)
        out[k] = spec[k].coerce(k, v, where)
    return out


def describe(spec: Mapping[str, Option]) -> str:
    return "\n".join(f"  {k}={o.form()}  {o.help} (default {o.default!r})" for k, o in spec.items())
