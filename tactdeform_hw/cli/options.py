"""The option vocabulary of ``tactdeform-hw``: one spelling per quantity, its unit in its name.

Every option that carries a unit says it (``--pulse-width-us``, ``--frequency-hz``, ``--hold-ms``,
``--current-ua``); currents are always in µA and polarity is always ``anodic`` or ``cathodic``.  An
earlier spelling (``--frequency``, ``--hold`` in seconds, ``timing --pulse-height`` as a DAC code) keeps
working for one release: it warns on stderr, is converted to the new unit, and is remembered, so an
error about its value names the flag the user actually typed.

The device layer reports a bad value as ``LimitError(field, value, limit)`` with its own field names
(``rate_hz``, ``electrode_count``); :func:`user_message` turns those into the flag of the command that
carried the value, through one table per command (:data:`FIELD_FLAGS`).
"""

from __future__ import annotations

import argparse
import math
import re
import sys
from collections.abc import Callable, Sequence
from typing import Any

from ..errors import LimitError, TactDeformError

#: Where a deprecated spelling was used: ``{canonical flag: flag typed}`` on the parsed namespace.
TYPED_ATTR = "_typed_flags"
#: Callables run on the parsed namespace before the command (conversions between old and new units).
FINISH_ATTR = "_finish"

POLARITIES = ("anodic", "cathodic")
#: The firmware's polarity code (``stim_mode`` in eTactileKit files, ``polarity`` in the scan model).
POLARITY_CODE = {"anodic": 1, "cathodic": 0}


def warn(prog: str, message: str) -> None:
    print(f"{prog}: warning: {message}", file=sys.stderr, flush=True)


def typed_flag(args: argparse.Namespace, flag: str) -> str:
    """The spelling of ``flag`` the user typed (a deprecated one, if that is what they used)."""
    typed: dict[str, str] = dict(getattr(args, TYPED_ATTR, None) or {})
    return typed.get(flag, flag)


def _remember(namespace: argparse.Namespace, canonical: str, typed: str) -> None:
    seen = dict(getattr(namespace, TYPED_ATTR, None) or {})
    seen[canonical] = typed
    setattr(namespace, TYPED_ATTR, seen)


class EarlierSpelling(argparse.Action):
    """An option that still takes an earlier spelling for one release: of the flag (:class:`DeprecatedAlias`)
    or of a value (:class:`PolarityCode`).  What :meth:`take` makes of the value is stored; an earlier
    spelling warns on stderr in the one sentence every such option uses, naming what to use instead."""

    def take(self, namespace: argparse.Namespace, values: Any, typed: str) -> tuple[Any, str | None, str]:
        """The value to store, the earlier spelling it came in (``None``: the current one) and the
        spelling to use instead.  An :class:`argparse.ArgumentTypeError` is a usage error naming the
        flag ``typed``."""
        raise NotImplementedError

    def __call__(
        self,
        parser: argparse.ArgumentParser,
        namespace: argparse.Namespace,
        values: Any,
        option_string: str | None = None,
    ) -> None:
        typed = option_string or self.option_strings[0]
        try:
            value, earlier, instead = self.take(namespace, values, typed)
        except argparse.ArgumentTypeError as exc:
            parser.error(f"argument {typed}: {exc}")
        if earlier is not None:
            warn(
                parser.prog, f"{earlier} is deprecated and will be removed in the next release; use {instead}"
            )
        setattr(namespace, self.dest, value)


class DeprecatedAlias(EarlierSpelling):
    """An earlier spelling of an option: warns, converts to the new unit, stores under the new dest."""

    def __init__(
        self,
        option_strings: Sequence[str],
        dest: str,
        *,
        canonical: str,
        scale: float | None = None,
        convert: Callable[[Any], Any] | None = None,
        note: str = "",
        **kwargs: Any,
    ) -> None:
        super().__init__(option_strings, dest, **kwargs)
        self.canonical = canonical
        self.scale = scale
        self.convert = convert
        self.note = note

    def take(self, namespace: argparse.Namespace, values: Any, typed: str) -> tuple[Any, str | None, str]:
        """The value in the new unit; the flag typed is remembered, so an error about the value names it."""
        if self.convert is not None:
            values = self.convert(values)
        elif self.scale is not None:
            values = values * self.scale
        _remember(namespace, self.canonical, typed)
        return values, typed, self.canonical + (f" ({self.note})" if self.note else "")


_UNIT_SUFFIXES = ("us", "ms", "s", "hz", "ua", "mm")


def add_option(
    parser: argparse.ArgumentParser,
    flag: str,
    *,
    old: Sequence[str] = (),
    old_scale: float | None = None,
    old_convert: Callable[[Any], Any] | None = None,
    old_note: str = "",
    old_type: Any = None,
    old_choices: Sequence[Any] | None = None,
    **kwargs: Any,
) -> argparse.Action:
    """``parser.add_argument(flag, **kwargs)`` plus hidden, warning aliases for its earlier spellings.

    ``old_scale`` multiplies an alias's value into the new unit (``--hold`` s → ``--hold-ms``: 1000);
    ``old_convert`` replaces that for a change of kind (a DAC code → µA).  The aliases share the dest, so
    the command's body reads one attribute whichever spelling was typed."""
    if "metavar" not in kwargs and kwargs.get("action") in (None, "store") and kwargs.get("choices") is None:
        unit = flag.rsplit("-", 1)[-1]
        kwargs["metavar"] = (
            unit.upper() if unit in _UNIT_SUFFIXES else flag.lstrip("-").upper().replace("-", "_")
        )
    action = parser.add_argument(flag, **kwargs)
    alias_type = old_type if old_type is not None else kwargs.get("type")
    for alias in old:
        parser.add_argument(
            alias,
            dest=action.dest,
            **({"type": alias_type} if alias_type is not None else {}),
            choices=old_choices,
            metavar=kwargs.get("metavar"),
            default=argparse.SUPPRESS,
            help=argparse.SUPPRESS,
            action=DeprecatedAlias,
            canonical=flag,
            scale=old_scale,
            convert=old_convert,
            note=old_note,
        )
    return action


def add_firmware_version(parser: argparse.ArgumentParser, *, help: str) -> None:
    """``--firmware v1.2|v2`` (default v1.2) for commands that run a model of the board rather than
    identify one, so there is no ``auto``."""
    parser.add_argument("--firmware", choices=("v1.2", "v2"), default="v1.2", help=help)


def add_firmware_src(parser: argparse.ArgumentParser, *, help: str) -> None:
    """``--firmware-src DIR``: the firmware's own tree (PlatformIO, with ``src/``) built on this machine
    and run in place of the Python model (docs/firmware-host-build.md), read as ``args.firmware_src``
    (``None`` when not given); ``help`` says what the command does with it."""
    parser.add_argument("--firmware-src", metavar="DIR", default=None, help=help)


def add_board(parser: argparse.ArgumentParser) -> None:
    """``--board`` and ``--switching-boards``: the emulated board's kind and its stacked switching boards,
    declared once so every command that models a board offers them alike."""
    parser.add_argument(
        "--board", choices=("compact", "large"), default="compact", help="board kind (default compact)"
    )
    parser.add_argument(
        "--switching-boards", type=int, default=1, help="stacked switching boards (default 1)"
    )


def add_pulse_width(parser: argparse.ArgumentParser, *, default: int | None, help: str) -> None:
    """``--pulse-width-us`` (earlier ``--pulse-width``), read as ``args.pulse_width``."""
    add_option(
        parser,
        "--pulse-width-us",
        old=("--pulse-width",),
        dest="pulse_width",
        type=int,
        default=default,
        help=help,
    )


def add_tracking_rate(parser: argparse.ArgumentParser, *, default: float | None, help: str) -> None:
    """``--rate-hz`` (earlier ``--rate``), the tracking rate of a synthetic trajectory, read as
    ``args.rate``."""
    add_option(parser, "--rate-hz", old=("--rate",), dest="rate", type=float, default=default, help=help)


def add_discharge(
    parser: argparse.ArgumentParser, *, help: str = "discharge time in µs (default 45)"
) -> None:
    """``--discharge-us`` (earlier ``--discharge``), default 45 µs, read as ``args.discharge``."""
    add_option(
        parser, "--discharge-us", old=("--discharge",), dest="discharge", type=int, default=45, help=help
    )


def add_frequency(
    parser: argparse.ArgumentParser, *, help: str = "stimulation rate in Hz (default 125)"
) -> None:
    """``--frequency-hz`` (earlier ``--frequency``), default 125 Hz, read as ``args.frequency``."""
    add_option(
        parser, "--frequency-hz", old=("--frequency",), dest="frequency", type=int, default=125, help=help
    )


def add_current(parser: argparse.ArgumentParser) -> None:
    """``--current-ua`` of a command that stimulates at one current, 0 (patterns only) by default."""
    parser.add_argument(
        "--current-ua", type=int, default=0, help="pulse current in µA, 10 µA steps, ≤ 10000 (default 0)"
    )


def add_finisher(parser: argparse.ArgumentParser, fn: Callable[[argparse.Namespace], None]) -> None:
    """Run ``fn(args)`` after parsing, before the command (see :func:`finish`)."""
    parser.set_defaults(**{FINISH_ATTR: [*(parser.get_default(FINISH_ATTR) or []), fn]})


def finish(args: argparse.Namespace) -> None:
    for fn in getattr(args, FINISH_ATTR, None) or []:
        fn(args)


# --- value kinds (argparse types: a value of the wrong kind is a usage error, exit status 2) ------------


def _number(text: str, unit: str) -> float:
    """``text`` as a float, or the parse error argparse shows naming the text and the unit expected (the
    ranges are each caller's own)."""
    try:
        return float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number of {unit}") from None


def duration(unit: str, *, to_s: bool = False) -> Callable[[str], float]:
    """A finite number ≥ 0 in ``unit``: a negative or infinite duration is refused while parsing.  With
    ``to_s`` a value in ms is returned in seconds (the unit the command's body works in)."""

    def parse(text: str) -> float:
        value = _number(text, unit)
        if not math.isfinite(value) or value < 0:
            raise argparse.ArgumentTypeError(f"{text} is out of range: a duration ≥ 0 {unit}")
        return value / 1000.0 if to_s and unit == "ms" else value

    parse.__name__ = f"duration in {unit}"
    return parse


def positive(unit: str) -> Callable[[str], float]:
    """A finite number > 0 in ``unit`` (a timeout, a rate)."""

    def parse(text: str) -> float:
        value = _number(text, unit)
        if not math.isfinite(value) or value <= 0:
            raise argparse.ArgumentTypeError(f"{text} is out of range: a number > 0 {unit}")
        return value

    parse.__name__ = f"number of {unit}"
    return parse


def polarity_code(text: str) -> int:
    """``anodic`` → 1, ``cathodic`` → 0 (the firmware's code)."""
    try:
        return POLARITY_CODE[text.strip().lower()]
    except KeyError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a polarity: anodic or cathodic") from None


class PolarityCode(EarlierSpelling):
    """``--polarity anodic|cathodic`` stored as the firmware's code; the earlier ``1``/``0`` still work,
    with a warning."""

    def take(self, namespace: argparse.Namespace, values: Any, typed: str) -> tuple[Any, str | None, str]:
        text = str(values).strip()
        if text in ("0", "1"):
            name = "anodic" if text == "1" else "cathodic"
            return int(text), f"{typed} {text}", f"{typed} {name}"
        return polarity_code(text), None, typed


# --- field names of the device layer → the flags that carried them --------------------------------------

_STIM = {
    "electrode_count": "--electrodes",
    "current_ua": "--current-ua",
    "pulse_width_us": "--pulse-width-us",
    "discharge_us": "--discharge-us",
    "rate_hz": "--frequency-hz",
    "polarity": "--polarity",
}

#: ``{command: {field: flag}}``.  A field a command does not take from its command line (``play`` takes
#: its rate from the pattern file) names where the value came from instead.  Checks written in the CLI
#: itself raise with the earlier flag (``--rate``); the table maps that to the current spelling too.
FIELD_FLAGS: dict[str, dict[str, str]] = {
    "send": {**_STIM, "pattern length": "--pattern (its length)", "pattern": "--pattern"},
    "play": {**_STIM, "rate_hz": "params.frequency of the pattern file"},
    "timing": {
        "electrodes": "--electrodes",
        "pulse_width_us": "--pulse-width-us",
        "pulse_height": "--pulse-height",
        "discharge_us": "--discharge-us",
        "rate_hz": "--frequency-hz",
        "polarity": "--polarity",
        "sense_height_raw": "--sense-height",
        "sense_width_us": "--sense-width-us",
        "sense_current_ua": "--sense-current-ua",
        "hv513_num": "--hv513",
        "pattern": "--pattern",
        "pattern length": "--pattern (its length)",
        "phases": "--phases",
        "current_ua": "--current-ua",
    },
    "render": {"current_ua": "--current-ua", "--rate": "--rate-hz", "--speed": "--speed-mm-s"},
    "study": {"current_ua": "--current-ua", "--rate": "--rate-hz"},
    "calibrate": {
        "pulse_width_us": "--pulse-width-us",
        "polarity": "--polarity",
        "cap_ua": "--max-ua",
        "participant": "--participant",
        "max_ua": "--max-ua",
    },
}

_FIELD_EQ = r"(?<![\w.\-\[]){field}="


def _timing_constants() -> frozenset[str]:
    from dataclasses import fields

    from tactdeform_hw.emulator.timed.timing import TimingModel

    return frozenset(f.name for f in fields(TimingModel))


def _show(value: Any) -> str:
    return repr(value) if isinstance(value, str) else str(value)


def flag_for(command: str | None, field: str, args: argparse.Namespace | None = None) -> str | None:
    """The flag (as typed) that carried the device-layer ``field`` in ``command``, or None."""
    table = FIELD_FLAGS.get(command or "", {})
    flag = table.get(field)
    if flag is None and field.startswith("--"):
        flag = field
    if flag is None:
        return None
    return typed_flag(args, flag) if args is not None else flag


def user_message(exc: BaseException, command: str | None, args: argparse.Namespace | None = None) -> str:
    """The one line a user reads for ``exc``: device-layer field names replaced by the flags typed."""
    if isinstance(exc, LimitError):
        field = str(exc.field)
        indexed = re.fullmatch(r"pattern\[(\d+)\]", field)
        if indexed and command in ("send", "timing"):
            return f"--pattern value {indexed.group(1)} ({_show(exc.value)}) is out of range: {exc.limit}"
        if command == "timing" and field in _timing_constants():
            return f"--set {field}={_show(exc.value)} is out of range: {exc.limit}"
        flag = flag_for(command, field, args)
        if flag is not None:
            return f"{flag} {_show(exc.value)} is out of range: {exc.limit}"
    text = str(exc)
    if isinstance(exc, TactDeformError):
        # a check written with the flag (``--repeat=0``) reads like the rest: ``--repeat 0``
        text = re.sub(
            r"(?<![\w-])(--[a-z][a-z0-9-]*)=(?=\S)",
            lambda m: (typed_flag(args, m.group(1)) if args is not None else m.group(1)) + " ",
            text,
        )
        for field in FIELD_FLAGS.get(command or "", {}):
            if field.startswith("--"):
                continue
            flag = flag_for(command, field, args)
            if flag is not None:
                text = re.sub(_FIELD_EQ.format(field=re.escape(field)), f"{flag} ", text)
    return text


def range_check(
    dest: str, flag: str, lo: float, hi: float, unit: str = "", *, step: int | None = None
) -> Callable[[argparse.Namespace], None]:
    """A finisher refusing ``args.<dest>`` outside ``[lo, hi]`` (or off ``step``) before the command runs,
    for a value the command would otherwise only meet deep inside (a file writer, a saved profile)."""

    def check(args: argparse.Namespace) -> None:
        value = getattr(args, dest, None)
        if value is None:
            return
        check_range(flag, value, lo, hi, unit)
        if step and value % step:
            raise LimitError(flag, value, f"a multiple of {step}" + (f" {unit}" if unit else ""))

    return check


def check_range(flag: str, value: Any, lo: float, hi: float, unit: str = "") -> None:
    """Refuse ``value`` outside ``[lo, hi]`` naming ``flag`` (a check the device layer does not make)."""
    if not (isinstance(value, (int, float)) and lo <= value <= hi):
        raise LimitError(flag, value, f"{lo:g} to {hi:g}" + (f" {unit}" if unit else ""))
