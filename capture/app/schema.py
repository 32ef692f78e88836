"""The settings schema: a setting is a dataclass field made with :func:`setting`, which carries its
``devices.options.Option`` (type from the default, help, range, choices) and how its flag is spelled.

From that one definition come the config file's keys and checks (``capture.app.config``), the
``PERFCAP_<SECTION>_<KEY>`` environment variables and the command-line flags (:func:`add_flags`), and
every value, from text (flags, environment) or from a file, goes through one parser,
:func:`parse_value` (``Option.coerce``).
"""

from __future__ import annotations

from dataclasses import Field, field, fields
from typing import TYPE_CHECKING, Any

from capture.errors import ConfigError
from devices.options import BadValueError, Option, shown

if TYPE_CHECKING:
    import argparse
    from collections.abc import Iterator


def setting(default: Any, help: str, *, min: float | None = None, max: float | None = None,  # noqa: A002 - Option's
            choices: tuple[str, ...] | None = None, flag: str | None = None, flag_help: str | None = None,
            metavar: str | None = None, repeat: bool = False) -> Any:
    """A settings field: its ``Option`` (type from the default; ``help`` says what the setting is) and how
    its flag is spelled.

    Args:
        flag: the flag, when not ``--<key-with-dashes>`` (``--no-<key>`` for a setting on by default).
        flag_help: the flag's help, when it says something else than ``help`` (``--no-tls``).
        repeat: the flag may be given several times; the values are joined with commas.
    """
    opt = Option(type(default), default, help, choices, min, max)
    return field(default=default, metadata={"option": opt, "flag": flag, "flag_help": flag_help, "metavar": metavar,
                                            "repeat": repeat})


def setting_fields(cls: type) -> Iterator[tuple[Field[Any], Option]]:
    """The settings fields of a settings dataclass, with their options."""
    for f in fields(cls):
        opt = f.metadata.get("option")
        if isinstance(opt, Option):
            yield f, opt


_TYPE_NAMES = {int: "an integer", float: "a finite number", bool: "true or false", str: "a string"}


def parse_value(opt: Option, key: str, value: Any, where: str, *, from_text: bool) -> Any:
    """A setting's value through the one value parser (``Option.parse``), said as a setting when it is
    bad (``bus.live_queue = 'x' must be an integer``). A value from text (flags, environment) is parsed
    after its surrounding spaces are dropped; a file's typed value must already have the setting's type.

    Raises:
        ConfigError: naming ``where``, the key and the expected form.
    """
    if from_text and isinstance(value, str):
        value = value.strip()
    elif not from_text:
        typ = opt.type
        ok = (isinstance(value, bool) if typ is bool else
              isinstance(value, int) and not isinstance(value, bool) if typ is int else
              isinstance(value, int | float) and not isinstance(value, bool) if typ is float else
              isinstance(value, typ))
        if not ok:
            raise ConfigError(f"{where}: {key} = {shown(value)} must be {_TYPE_NAMES[typ]}", source=where)
    try:
        return opt.parse(value)
    except BadValueError as exc:
        what = {"type": f"must be {_TYPE_NAMES.get(opt.type, opt.form())}",
                "choice": f"must be one of {', '.join(opt.choices or ())}"}.get(exc.problem)
        raise ConfigError(f"{where}: {key} = {shown(value)} {what or opt.problem_text(exc.problem)}",
                          source=where) from None


# -- flags --------------------------------------------------------------------------------------------
def flag_name(f: Field[Any], opt: Option) -> str:
    given = f.metadata.get("flag")
    if isinstance(given, str):
        return given
    name = f.name.replace("_", "-")
    return f"--no-{name}" if opt.type is bool and opt.default else f"--{name}"


def add_flags(parser: argparse.ArgumentParser, cls: type) -> None:
    """One flag per setting of ``cls``; a flag left out leaves the setting to the config (None). Values
    stay text here: :func:`flag_values` parses them, so a bad one is the same one-line error as in a
    config file."""
    for f, opt in setting_fields(cls):
        flag = flag_name(f, opt)
        if opt.type is bool:
            parser.add_argument(flag, dest=f.name, action="store_const", const=not opt.default, default=None,
                                help=f.metadata.get("flag_help") or opt.help)
        else:
            parser.add_argument(flag, dest=f.name, action="append" if f.metadata.get("repeat") else "store",
                                default=None, metavar=f.metadata.get("metavar"),
                                help=f.metadata.get("flag_help") or opt.help)


def flag_values(args: argparse.Namespace, cls: type) -> dict[str, Any]:
    """The settings the flags of :func:`add_flags` gave, parsed (``repeat`` flags joined with commas).

    Raises:
        ConfigError: a value is not of its setting's form, naming the flag.
    """
    given = vars(args)
    out: dict[str, Any] = {}
    for f, opt in setting_fields(cls):
        v = given.get(f.name)
        if v is None:
            continue
        if f.metadata.get("repeat"):
            v = ",".join(v)
        out[f.name] = v if opt.type is bool else parse_value(opt, flag_name(f, opt), v, "command line",
                                                             from_text=True)
    return out
