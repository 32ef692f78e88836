"""Typed options for transports and devices, given as URL query keys or config tables.

Each Transport or Device class declares ``options: dict[str, Option]``; values are coerced and
checked here, and an unknown key or a bad value raises ``ConfigError`` that shows the expected form.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from capture.errors import ConfigError

if TYPE_CHECKING:
    from collections.abc import Mapping

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

    def form(self) -> str:
        if self.choices:
            return "|".join(self.choices)
        return {int: "INT", float: "NUMBER (finite)", bool: "true|false", str: "TEXT"}.get(self.type, "VALUE")

    def parse(self, value: Any) -> Any:
        """``value`` as this option's type, checked against its choices and range: the one value parser of
        device options, transport options and settings.

        Raises:
            BadValueError: with ``.problem`` ``"type"``, ``"choice"`` or ``"range"``.
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
        except (TypeError, ValueError):
            raise BadValueError("type") from None
        if self.choices and v not in self.choices:
            raise BadValueError("choice")
        if (self.min is not None and v < self.min) or (self.max is not None and v > self.max):
            raise BadValueError("range")
        return v

    def range_text(self) -> str:
        """The bounds in words (``within [1, 5]``, ``at least 0``); ``any value`` for an option without any."""
        if self.min is not None and self.max is not None:
            return f"within [{self.min:g}, {self.max:g}]"
        if self.min is not None:
            return f"at least {self.min:g}"
        return f"at most {self.max:g}" if self.max is not None else "any value"

    def coerce(self, key: str, value: Any, where: str) -> Any:
        """:meth:`parse`, with a bad value said as a URL or device option (``rate='x' is not NUMBER``).

        Raises:
            ConfigError: naming ``where``, the key and the expected form.
        """
        try:
            return self.parse(value)
        except BadValueError as exc:
            what = {"type": f"is not {self.form()}", "choice": f"must be one of {self.form()}",
                    "range": f"must be {self.range_text()}"}[exc.problem]
            raise ConfigError(f"{where}: option {key}={value!r} {what}", source=where) from None


class BadValueError(ValueError):
    """A value an ``Option`` does not take; ``problem`` is ``"type"``, ``"choice"`` or ``"range"``."""

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
