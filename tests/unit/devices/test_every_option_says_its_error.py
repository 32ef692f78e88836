"""Every option of every device kind and transport scheme turns any bad value into one ``ConfigError``.

The class of bug: building the message for one kind of problem (a wrong choice) must not trip over what
another kind needs (the bounds of an option that has none). A seeded sweep of hostile values over every
declared option, through :meth:`Option.coerce` (URL and device options) and ``parse_value`` (settings).
"""

from __future__ import annotations

import math
import random
from typing import TYPE_CHECKING

import pytest

from capture.app.schema import parse_value
from capture.errors import ConfigError
from devices import device_class, known_kinds
from devices.transports import known_schemes, transport_class

if TYPE_CHECKING:
    from devices.options import Option

HOSTILE = [None, "", " ", "x", "nan", "inf", "-inf", "1e999", "-1", "0", "1.5", "99999999999999999999", True,
           [], {}, float("nan"), float("inf"), -1e308, 1e308, 2**70, -(2**70), "recorded", "now", "csv", "é\x00"]


def _declared() -> list[tuple[str, str, Option]]:
    out: list[tuple[str, str, Option]] = []
    for kind in known_kinds():
        out += [(f"device {kind}", k, o) for k, o in device_class(kind).options.items()]
    for scheme in known_schemes():
        out += [(f"{scheme}://", k, o) for k, o in transport_class(scheme).options.items()]
    return out


DECLARED = _declared()


def test_there_are_options_with_and_without_bounds_and_choices():
    assert len(DECLARED) > 30
    assert any(o.choices for _, _, o in DECLARED) and any(o.min is not None for _, _, o in DECLARED)
    assert any(o.min is None and o.max is None and not o.choices for _, _, o in DECLARED)


@pytest.mark.parametrize(("owner", "key", "opt"), DECLARED, ids=[f"{w}-{k}" for w, k, _ in DECLARED])
def test_any_value_is_taken_or_refused_with_a_config_error(owner, key, opt):
    rng = random.Random(f"{owner}/{key}")
    values = [*HOSTILE, *(rng.uniform(-1e6, 1e6) for _ in range(20)), *(rng.randint(-10**6, 10**6) for _ in range(20))]
    if opt.min is not None:
        values += [opt.min - 1, opt.min, opt.min - 1e-9]
    if opt.max is not None:
        values += [opt.max + 1, opt.max, opt.max + 1e-9]
    for v in values:
        for as_setting in (False, True):
            try:
                got = (parse_value(opt, key, v, owner, from_text=isinstance(v, str)) if as_setting
                       else opt.coerce(key, v, owner))
            except ConfigError as exc:
                assert key in str(exc) and "\n" not in str(exc), exc
                continue
            # what is taken is of the option's type, finite, among its choices and within its bounds
            assert isinstance(got, opt.type), (v, got)
            if isinstance(got, float):
                assert math.isfinite(got)
            assert not opt.choices or got in opt.choices
            assert opt.min is None or got >= opt.min
            assert opt.max is None or got <= opt.max
