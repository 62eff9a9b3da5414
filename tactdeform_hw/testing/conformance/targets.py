"""Targets of the conformance checks: the emulator on each transport (CI), or a real board (opt-in).

With no device chosen, the checks run on the four emulated targets — the pyserial URL handler
(``etactile://``), a real pseudo-terminal (``pty``), a TCP port served with the Wi-Fi build's rules
(``tcp``) and the emulated USB device through pyusb (``usb-emulator``); each serves the timed model on the
wall clock, so the rhythm checks run on all of them.  The v2 checks run on the same transports serving
firmware v2 (:data:`V2_TARGETS`).  A target name's ``firmware=`` decides which module's checks it gets,
the other module's are skipped with the reason.  ``--etactile-device`` (the plugin's option; the
package's own suite also reads its ``--device``) picks one target instead:

* ``etactile://[?options]``, ``emulator``, ``pty[?firmware=v2]``, ``tcp[?firmware=v2]``,
  ``usb-emulator[?options]`` — an emulated board (``etactile://?timed=0`` and ``emulator``: the untimed
  one, which has no rhythm to check);
* a serial port (``/dev/ttyACM0``, ``COM3``) or ``usb:303a:1001[:SERIAL]`` — a real board.  Skipped, with
  the reason, when the board is not attached or (for ``usb:``) pyusb or libusb is missing.

Tunables for the bench come from the environment: ``ETACTILE_REPLY_BUDGET_MS`` (default 20),
``ETACTILE_QUIET_MS`` (how long "no reply" must last; default 30 on an emulator, 60 on a board).

At the end of the run the terminal summary prints an "eTactileKit conformance report" with the figures
each check measured (latencies, rhythm); ``--junitxml`` carries the same figures as test properties.
"""

from __future__ import annotations

import errno
import os
import sys
import time
import urllib.parse as urlparse
import uuid
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import Any

import pytest

from tactdeform_hw.device import open_port
from tactdeform_hw.errors import ConfigurationError, MissingDependencyError, TransportError
from tactdeform_hw.protocol.firmware import FIRMWARES
from tactdeform_hw.protocol.state import BoardState

EMULATED_TARGETS = ("etactile://", "pty", "tcp", "usb-emulator")
#: the same transports serving firmware v2 (the suite in ``test_conformance_v2.py``)
V2_TARGETS = (
    "etactile://?firmware=v2&timed=0",
    "etactile://?firmware=v2",
    "pty?firmware=v2",
    "tcp?firmware=v2",
    "usb-emulator?firmware=v2",
)
REPLY_TIMEOUT_S = 0.5


def _env_ms(name: str, default: float) -> float:
    raw = os.environ.get(name)
    if not raw:
        return default
    try:
        return float(raw)
    except ValueError:
        raise pytest.UsageError(f"{name}={raw!r} is not a number of milliseconds") from None


@dataclass
class Target:
    """One device the checks run against.

    ``timed``: host-observable timing is the firmware's (a board, or an emulated board on the wall
    clock); only ``etactile://?timed=0`` serves the untimed emulator, which answers at once and has no
    tick.  ``state``: the firmware's registers (emulated targets only).  ``firmware``: the version an
    emulated target serves (``None`` for a board: the suite does not assume it).
    """

    name: str
    kind: str  # "emulator" or "board"
    route: str  # "url", "pty", "usb" or "serial"
    timed: bool
    make_port: Callable[[], Any]
    state: Callable[[], BoardState] | None = None
    hv513_expected: int | None = None
    settle_fn: Callable[[int], None] | None = None
    cleanup: list[Callable[[], None]] = field(default_factory=list)
    firmware: str | None = "v1.2"
    #: The identification's wait before its first byte: 0 for an emulated board made for this one test
    #: (no earlier program wrote to it), the driver's default for a board on the bench.
    settle_s: float | None = None

    @property
    def is_board(self) -> bool:
        return self.kind == "board"

    @property
    def quiet_s(self) -> float:
        return _env_ms("ETACTILE_QUIET_MS", 60.0 if self.is_board else 30.0) / 1000.0

    @property
    def reply_budget_s(self) -> float:
        return _env_ms("ETACTILE_REPLY_BUDGET_MS", 20.0) / 1000.0

    def open(self) -> Any:
        """A new, opened port with DTR and RTS low (an ESP32 must not be reset by the suite)."""
        port = self.make_port()
        for line in ("dtr", "rts"):
            if hasattr(port, line):
                setattr(port, line, False)
        port.open()
        return port

    def settle(self, commands: int = 1) -> None:
        """Wait until the device has read everything sent (``commands`` with a payload, one per tick)."""
        if self.settle_fn is not None:
            self.settle_fn(commands)
        else:
            time.sleep((commands + 4) / 1000.0 + (0.01 if self.is_board else 0.0))


# --- building targets ----------------------------------------------------------------------------------


def name_firmware(name: str) -> str | None:
    """The firmware an emulated target name asks for (``firmware=v2`` in its query, the declared version
    of a ``firmware_src=`` tree; v1.2 otherwise); ``None`` for a board, whose version the name does not
    tell."""
    if is_board_name(name):
        return None
    query = urlparse.parse_qs(name.partition("?")[2])
    if "firmware_src" in query:
        from tactdeform_hw.emulator.hostbuild.statemap import declared_firmware

        try:
            return declared_firmware(query["firmware_src"][-1], f"--device {name}: firmware_src")
        except ConfigurationError as exc:
            raise pytest.UsageError(str(exc)) from None
    fw = query.get("firmware", ["v1.2"])[-1]
    if fw not in FIRMWARES:
        raise pytest.UsageError(f"--device {name}: firmware={fw!r} is not one of {', '.join(FIRMWARES)}")
    return fw


def _server_firmware(name: str) -> str:
    """``pty[?firmware=v1.2|v2]`` and ``tcp[?firmware=...]`` take that option only."""
    unknown = set(urlparse.parse_qs(name.partition("?")[2])) - {"firmware"}
    if unknown:
        raise pytest.UsageError(f"--device {name}: unknown option(s) {sorted(unknown)}; only firmware=")
    return name_firmware(name) or "v1.2"


def _settle_on(board: Any, server: Any = None, written: list[int] | None = None) -> Callable[[int], None]:
    """Wait until a real-time board's parser has read everything sent (generous: the machine may be
    loaded).  Behind a server, first until the server has received every byte the ports wrote."""
    from tactdeform_hw.emulator.serving.realtime import settle

    def wait(commands: int) -> None:
        deadline = time.monotonic() + 5.0
        while server is not None and written is not None and server.bytes_in < written[0]:
            if time.monotonic() > deadline:
                break
            time.sleep(0.0005)
        settle(board, timeout_s=5.0)

    return wait


class _CountingPort:
    """A port that counts the bytes written through it (so a settle can wait for the server to have
    received them all)."""

    def __init__(self, port: Any, counter: list[int]) -> None:
        object.__setattr__(self, "_port", port)
        object.__setattr__(self, "_counter", counter)

    def write(self, data: bytes) -> Any:
        n = self._port.write(data)
        self._counter[0] += len(data)
        return n

    def __getattr__(self, name: str) -> Any:
        return getattr(self._port, name)

    def __setattr__(self, name: str, value: Any) -> None:
        setattr(self._port, name, value)


def _url_target(name: str) -> Target:
    from tactdeform_hw.emulator.serving.realtime import RealtimeEmulator
    from tactdeform_hw.emulator.serving.urlhandler.protocol_etactile import forget_shared, shared_emulator

    query = name.partition("?")[2] if name.startswith("etactile://") else ""
    shared = f"conformance-{uuid.uuid4().hex[:8]}"
    url = f"etactile://{shared}" + (f"?{query}" if query else "")
    first = open_port(url, timeout=REPLY_TIMEOUT_S)
    first.open()  # creates the shared emulator the test's ports talk to
    emu = shared_emulator(shared)
    assert emu is not None
    timed = isinstance(emu, RealtimeEmulator)
    t = Target(
        settle_s=0.0,
        name=name,
        kind="emulator",
        route="url",
        timed=timed,
        make_port=lambda: open_port(url, timeout=REPLY_TIMEOUT_S),
        state=emu.state,
        hv513_expected=emu.board.detect_hv513(),
        settle_fn=_settle_on(emu) if timed else (lambda n: None),
        firmware=emu.firmware.name if emu.firmware is not None else "",
    )
    t.cleanup += [first.close, lambda: forget_shared(shared)]
    return t


def _served_target(name: str, route: str, firmware: str, server: Any, open_raw: Callable[[], Any]) -> Target:
    """A target on a started server of the timed board (pty or TCP): the port counts the bytes written so
    the settle step can wait for the board to have taken them all, and the server stops at clean-up."""
    written = [0]
    t = Target(
        settle_s=0.0,
        name=name,
        kind="emulator",
        route=route,
        timed=True,
        make_port=lambda: _CountingPort(open_raw(), written),
        state=server.state,
        hv513_expected=server.board.board.detect_hv513(),
        settle_fn=_settle_on(server.board, server, written),
        firmware=firmware,
    )
    t.cleanup.append(server.stop)
    return t


def _pty_target(name: str) -> Target:
    if sys.platform == "win32":
        pytest.skip("the pty target needs a POSIX pseudo-terminal")
    from tactdeform_hw.emulator.serving.pty_server import PtyServer

    firmware = _server_firmware(name)
    server = PtyServer(firmware=firmware)  # the timed board on the wall clock
    server.start()
    return _served_target(
        name, "pty", firmware, server, lambda: open_port(server.path, timeout=REPLY_TIMEOUT_S)
    )


def _tcp_target(name: str) -> Target:
    from tactdeform_hw.emulator.serving.tcp_server import TcpServer

    # the Wi-Fi build's rules: one client at a time, TCP flow control
    firmware = _server_firmware(name)
    server = TcpServer(port=0, firmware=firmware)
    server.start()

    def open_raw() -> Any:
        import serial

        return serial.serial_for_url(
            server.url, do_not_open=True, timeout=REPLY_TIMEOUT_S, write_timeout=REPLY_TIMEOUT_S
        )

    return _served_target(name, "tcp", firmware, server, open_raw)


def _usb_emulator_target(name: str) -> Target:
    pytest.importorskip(
        "usb.core", reason="the usb-emulator target needs pyusb (pip install 'tactdeform_hw[usb]')"
    )
    from tactdeform_hw.device.driver.usb_transport import UsbCdcPort
    from tactdeform_hw.emulator.serving.usb_backend import backend_from_name

    backend = backend_from_name(name)
    dev = backend.device

    def settle_usb(commands: int) -> None:
        dev.settle()

    def make_port() -> Any:
        return UsbCdcPort(
            0x303A, 0x1001, backend=backend, timeout=REPLY_TIMEOUT_S, write_timeout=REPLY_TIMEOUT_S, name=name
        )

    return Target(
        settle_s=0.0,
        name=name,
        kind="emulator",
        route="usb",
        timed=True,
        make_port=make_port,
        state=dev.state,
        hv513_expected=dev.emulator.board.detect_hv513(),
        settle_fn=settle_usb,
        firmware=dev.firmware.name,
    )


def _serial_board_target(name: str) -> Target:
    if sys.platform != "win32" and not os.path.exists(name):
        pytest.skip(
            f"no board at {name}: plug the eTactileKit in, or pass --device with its port "
            "(`tactdeform-hw ports` lists candidates)"
        )
    probe = open_port(name, timeout=REPLY_TIMEOUT_S)
    probe.dtr = probe.rts = False
    try:
        probe.open()
    except Exception as exc:  # noqa: BLE001 - any failure to open means no usable board here
        pytest.skip(f"cannot open {name} ({exc}); is the board attached and the port free?")
    probe.close()
    return Target(name=name, kind="board", route="serial", timed=True, firmware=None,
                  make_port=lambda: open_port(name, timeout=REPLY_TIMEOUT_S))  # fmt: skip


def _usb_board_target(name: str) -> Target:
    try:
        from tactdeform_hw.protocol.constants import BAUD_RATE
        from tactdeform_hw.transports import port_for_name

        def usb_port_for_name(name: str, *, timeout: float) -> Any:  # usb:… and usb-emulator… alike
            return port_for_name(name, timeout=timeout, baudrate=BAUD_RATE)

        probe = usb_port_for_name(name, timeout=REPLY_TIMEOUT_S)
        probe.open()
    except MissingDependencyError as exc:
        pytest.skip(str(exc))
    except TransportError as exc:
        if exc.code == errno.ENODEV or "no USB backend" in str(exc):
            pytest.skip(str(exc))
        raise  # attached but unusable (permissions, busy): the message says what to fix
    probe.close()
    return Target(name=name, kind="board", route="usb", timed=True, firmware=None,
                  make_port=lambda: usb_port_for_name(name, timeout=REPLY_TIMEOUT_S))  # fmt: skip


_UNAVAILABLE: dict[str, str] = {}  # board name -> why it was skipped (probed once per session)


def build_target(name: str) -> Target:
    if name in _UNAVAILABLE:
        pytest.skip(_UNAVAILABLE[name])
    try:
        return _build_target(name)
    except pytest.skip.Exception as exc:
        if is_board_name(name):
            _UNAVAILABLE[name] = str(exc.msg)
        raise


def _build_target(name: str) -> Target:
    if name in ("emulator", "emu", "") or name.startswith("etactile://"):
        return _url_target(name or "etactile://")
    if name == "pty" or name.startswith("pty?"):
        return _pty_target(name)
    if name == "tcp" or name.startswith("tcp?"):
        return _tcp_target(name)
    if name == "usb-emulator" or name.startswith("usb-emulator?"):
        return _usb_emulator_target(name)
    if name.startswith("usb:"):
        return _usb_board_target(name)
    if "://" in name:
        raise pytest.UsageError(f"--device {name}: only etactile:// URLs are emulated targets")
    return _serial_board_target(name)


def is_board_name(name: str) -> bool:
    return not (
        name in ("emulator", "emu", "pty", "tcp")
        or name.startswith(("etactile://", "usb-emulator", "pty?", "tcp?"))
    )


# --- pytest plumbing ---------------------------------------------------------------------------------------


def chosen_device(config: pytest.Config) -> str | None:
    """The one target named on the command line: ``--etactile-device`` (the plugin's option), else the
    package's own suite's ``--device``; None when neither was given (every emulated target)."""
    for option in ("--etactile-device", "--device"):
        value = config.getoption(option, default=None)
        if value:
            return str(value)
    return None


def target_params(config: pytest.Config, firmware: str, defaults: tuple[str, ...]) -> list[Any]:
    """The targets a module of ``firmware``'s checks runs on: the chosen device, or ``defaults``.  A board
    is marked ``hardware``; an emulated target serving another firmware is skipped with the reason."""
    chosen = chosen_device(config)
    params = []
    for n in [chosen] if chosen else list(defaults):
        marks: list[Any] = [pytest.mark.hardware] if is_board_name(n) else []
        served = name_firmware(n)
        if served not in (None, firmware):
            what = served or "(none declared)"
            marks.append(
                pytest.mark.skip(reason=f"{n} serves firmware {what}: these are the {firmware} checks")
            )
        params.append(pytest.param(n, id=n, marks=marks))
    return params


def generate_v1_2_targets(metafunc: pytest.Metafunc) -> None:
    """Parametrize ``target_name``: the chosen device, or every emulated v1.2 target."""
    if "target_name" in metafunc.fixturenames:
        metafunc.parametrize("target_name", target_params(metafunc.config, "v1.2", EMULATED_TARGETS))


@contextmanager
def built_target(name: str) -> Iterator[Target]:
    """The target ``name`` built for one check (:func:`build_target`), its cleanups run in reverse order
    when the check ends, however it ends: the fixtures of both versions' checks hold their targets so."""
    t = build_target(name)
    try:
        yield t
    finally:
        for fn in reversed(t.cleanup):
            fn()


@pytest.fixture(name="target")
def target_fixture(target_name: str) -> Iterator[Target]:
    with built_target(target_name) as t:
        yield t


#: (target, check: figure, text) of every figure measured in this run, until the summary prints them
REPORT: list[tuple[str, str, str]] = []


@pytest.fixture(name="report")
def report_fixture(request: pytest.FixtureRequest, target: Target) -> Callable[[str, str], None]:
    """``report(figure, text)``: a measured figure for the conformance report (and junit properties)."""
    check = request.node.originalname

    def note(figure: str, text: str) -> None:
        REPORT.append((target.name, f"{check}: {figure}", text))
        request.node.user_properties.append((figure, text))

    return note


def write_report(terminalreporter: Any) -> None:
    """The "eTactileKit conformance report" section, once (the figures are taken as they are written)."""
    if not REPORT:
        return
    rows = list(REPORT)
    REPORT.clear()
    tr = terminalreporter
    tr.section("eTactileKit conformance report")
    for name in dict.fromkeys(t for t, _, _ in rows):
        tr.write_line(f"target {name}:")
        for _, figure, text in (r for r in rows if r[0] == name):
            tr.write_line(f"  {figure:<58} {text}")
