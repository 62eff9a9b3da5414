"""Checks made before a command opens its device: every output it will write can be written, the
optional packages its outputs need are installed, and ``--device`` names something that can be a port.

A study run stimulates for minutes before it writes its report; an output that cannot be written found
only then costs the session.  So each command's outputs are listed here (:data:`OUTPUTS`) and probed
first: a file output's directory must exist and take a new file, an existing file must be writable, a
directory output must be creatable.  The probe leaves nothing behind.
"""

from __future__ import annotations

import argparse
import os
import stat
import tempfile
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from ..errors import ConfigurationError, MissingDependencyError, OutputError, install_command
from .options import typed_flag

FILE = "file"
DIR = "directory"

#: ``{command: ((dest, flag, kind), ...)}``; ``--audit-log`` is checked for every command that has it.
OUTPUTS: dict[str, tuple[tuple[str, str, str], ...]] = {
    "send": (),
    "play": (("gif", "--gif", FILE),),
    "export": (("out", "--out", FILE), ("array_out", "--array-out", FILE), ("gif", "--gif", FILE)),
    "render": (("frames", "--frames", FILE), ("gif", "--gif", FILE), ("strip", "--strip", FILE)),
    "study": (("out", "--out", DIR),),
    "timing": (("vcd", "--vcd", FILE), ("events", "--events", FILE), ("png", "--png", FILE)),
    "emulate": (("trace", "--trace", FILE),),
    "calibrate": (),  # its profile file: see _calibrate_outputs
}

#: Output flags whose file needs an optional extra: ``{flag: (module, package, extra)}``.
NEEDS_EXTRA: dict[str, tuple[str, str, str]] = {
    "--gif": ("matplotlib", "matplotlib", "plot"),
    "--png": ("matplotlib", "matplotlib", "plot"),
    "--strip": ("matplotlib", "matplotlib", "plot"),
    "--vcd": ("vcd", "pyvcd", "trace"),
}


@contextmanager
def writing(flag: str, path: str | os.PathLike[str]) -> Iterator[None]:
    """Writes to the output of ``flag``: an operating-system error while writing (a buffered write fails
    only at its flush, with no file name) becomes an :class:`OutputError` naming the option and the
    path."""
    try:
        yield
    except OSError as exc:
        raise OutputError(flag, str(path), exc.strerror or str(exc)) from exc


#: The picture formats each output writes, named by the file's suffix: a mismatching suffix is refused
#: (a viewer trusts the suffix, and PNG bytes in a .jpg are a broken file to it).
PICTURE_SUFFIXES: dict[str, tuple[str, ...]] = {
    "--png": (".png",),
    "--strip": (".png",),
    "--gif": (".gif",),
}


def check_suffix(path: str, flag: str) -> None:
    """Refuse a picture output whose suffix names another format than the one written."""
    want = PICTURE_SUFFIXES.get(flag.split("/")[0])
    if want is None:
        return
    suffix = Path(path).suffix.lower()
    if suffix not in want:
        raise ConfigurationError(
            f"{flag} {path}: writes {want[0][1:].upper()}, but the suffix {suffix or '(none)'} names "
            f"another format; give a {' or '.join(want)} file"
        )


def _calibrate_outputs(args: argparse.Namespace) -> list[tuple[str, str, str]]:
    from .calibrate import profile_targets

    _pid, out = profile_targets(args)
    flag = "--out" if getattr(args, "out", None) else "--participant"
    found = [(str(out), flag, FILE)]
    if getattr(args, "calibration_out", None):
        found.append((str(args.calibration_out), "--calibration-out", FILE))
    return found


def planned_outputs(args: argparse.Namespace) -> list[tuple[str, str, str]]:
    """``(path, flag as typed, kind)`` of every output the parsed command will write."""
    command = getattr(args, "command", None) or ""
    found: list[tuple[str, str, str]] = []
    for dest, flag, kind in OUTPUTS.get(command, ()):
        value = getattr(args, dest, None)
        if isinstance(value, (str, os.PathLike)) and str(value):
            found.append((str(value), typed_flag(args, flag), kind))
    if command == "calibrate":
        found += _calibrate_outputs(args)
    audit = getattr(args, "audit_log", None)
    if audit:
        found.append((str(audit), "--audit-log", FILE))
    return found


def check_output(path: str, flag: str, kind: str = FILE) -> None:
    """Refuse an output that cannot be written, naming the flag; nothing is left behind by the check."""
    p = Path(path)
    where = f"{flag} {path}"
    if kind == DIR:
        if p.exists():
            if not p.is_dir():
                raise ConfigurationError(
                    f"{where}: is a file, not a directory; give a directory for the report"
                )
            if not os.access(p, os.W_OK | os.X_OK):
                raise ConfigurationError(f"{where}: the directory is not writable")
            return
        base = p.parent
        while not base.exists() and base != base.parent:
            base = base.parent
        if not base.is_dir():
            raise ConfigurationError(f"{where}: {base} is a file, not a directory")
        _probe_dir(base, where)
        return
    if p.is_dir():
        raise ConfigurationError(f"{where}: is a directory; give a file name")
    parent = p.parent
    if not parent.exists():
        raise ConfigurationError(f"{where}: the directory {parent} does not exist")
    if not parent.is_dir():
        raise ConfigurationError(f"{where}: {parent} is a file, not a directory")
    if p.exists():
        try:
            with open(p, "ab"):
                pass
        except OSError as exc:
            raise ConfigurationError(f"{where}: cannot be written ({exc.strerror or exc})") from exc
        return
    try:
        with open(p, "xb"):
            pass
    except OSError as exc:
        raise ConfigurationError(f"{where}: cannot be created ({exc.strerror or exc})") from exc
    try:
        p.unlink()
    except OSError:  # pragma: no cover - created a moment ago
        pass


def _probe_dir(base: Path, where: str) -> None:
    try:
        made = tempfile.mkdtemp(prefix=".tactdeform-probe-", dir=base)
    except OSError as exc:
        raise ConfigurationError(
            f"{where}: cannot create a directory in {base} ({exc.strerror or exc})"
        ) from exc
    os.rmdir(made)


def check_extras(args: argparse.Namespace, outputs: list[tuple[str, str, str]]) -> list[str]:
    """Refuse an output whose optional package is missing; return warnings for what will be left out."""
    import importlib.util

    def have(module: str) -> bool:
        try:
            return importlib.util.find_spec(module) is not None
        except (ImportError, ValueError):
            return False

    for path, flag, _kind in outputs:
        base = flag.split("/")[0]
        if base == "--trace" and Path(path).suffix.lower() == ".vcd":
            base = "--vcd"
        need = NEEDS_EXTRA.get(base)
        if need is None:
            continue
        module, package, extra = need
        if not have(module):
            raise MissingDependencyError(package, extra, f"{flag} {path}")
        if extra == "plot" and not have("PIL"):
            raise MissingDependencyError("pillow", extra, f"{flag} {path}")
    warnings: list[str] = []
    if getattr(args, "command", None) == "study" and not getattr(args, "no_pictures", False):
        if not (have("matplotlib") and have("PIL")):
            warnings.append(
                "the report will have no pictures: they need matplotlib and Pillow, "
                f"{install_command('plot')} (or pass --no-pictures)"
            )
    return warnings


# --- --device -------------------------------------------------------------------------------------------

_NOT_PATHS = ("emulator", "emu", "", "usb-emulator")


def check_device(args: argparse.Namespace) -> None:
    """A ``--device`` that is a file system path must be a character device (a serial port or a pty)."""
    name = getattr(args, "device", None)
    if not isinstance(name, str) or name in _NOT_PATHS or "://" in name or name.lower().startswith("usb:"):
        return
    if os.sep not in name and "/" not in name:
        return  # COM3 and the like: the serial layer says what it finds
    try:
        mode = os.stat(name).st_mode
    except FileNotFoundError:
        raise ConfigurationError(
            f"--device {name}: no such device; 'tactdeform-hw ports' lists the boards "
            "it can see, and --device emulator needs none"
        ) from None
    except OSError as exc:
        raise ConfigurationError(f"--device {name}: cannot be examined ({exc.strerror or exc})") from exc
    if not stat.S_ISCHR(mode):
        what = (
            "a directory"
            if stat.S_ISDIR(mode)
            else "a regular file"
            if stat.S_ISREG(mode)
            else "not a device"
        )
        raise ConfigurationError(
            f"--device {name} is not a serial port ({what}); 'tactdeform-hw ports' lists "
            "the boards it can see"
        )


def preflight(args: argparse.Namespace, warn: Callable[[str], Any] | None = None) -> None:
    """Every check that must pass before the command opens its device or writes a byte."""
    check_device(args)
    outputs = planned_outputs(args)
    for path, flag, kind in outputs:
        check_suffix(path, flag)
        check_output(path, flag, kind)
    for message in check_extras(args, outputs):
        if warn is not None:
            warn(message)
