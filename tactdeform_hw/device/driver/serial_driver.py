"""The eTactileKit driver over any pyserial-compatible port: a real path, a URL, or an in-process port.

It never knows which of these it holds; it asks the port what it can do.  Opening a real port must not
reset the board: pyserial asserts DTR and RTS on open, which an ESP32 can read as a reset request, so the
port is created unopened, both lines are set low, and only then is it opened.

**One owner per board.**  A port opened by path (:class:`ExclusivePort`) is locked before its first byte:
``flock(LOCK_EX | LOCK_NB)`` (pyserial's ``exclusive=True``), then ``TIOCEXCL``, which makes the kernel
refuse any further open of the terminal to everyone but root.  A second program — another command, or a
script using the library — gets :class:`~tactdeform_hw.errors.DeviceBusyError` naming the device and the
process holding it (from ``/proc/locks`` and ``/proc/*/fd``); nothing is written.  The lock belongs to the
open file description, which the owner's guardian (:mod:`.guardian`) shares, so it outlives an owner
killed with SIGKILL until the guardian has switched the board off.

**A guardian per guardable port.**  A port that declares ``guardable = True`` gets a guardian process
when the device opens (see :mod:`.guardian`): it switches the board off if the owner dies without running
code.  The in-process emulator declares nothing: the board it models dies with the process.
"""

from __future__ import annotations

import errno
import sys
from typing import Any, Protocol

from tactdeform_hw.clock import Clock
from tactdeform_hw.device.driver.audit import AuditLog
from tactdeform_hw.device.driver.base import Device
from tactdeform_hw.device.driver.config import StimConfig
from tactdeform_hw.device.driver.firmware_probe import (
    SETTLE_S,
    Detection,
    FirmwareMismatchError,
    UnidentifiedBoardError,
    check_firmware,
    detect_firmware,
)
from tactdeform_hw.device.driver.holders import find_holders
from tactdeform_hw.device.driver.pacing import Pacer, default_pacer
from tactdeform_hw.device.participant.mapping import ChannelMapping
from tactdeform_hw.device.safety.guard import SafetyGuard
from tactdeform_hw.device.safety.guardian import Guardian, GuardianError, pace_for
from tactdeform_hw.errors import (
    DeviceBusyError,
    DeviceGoneError,
    DeviceTimeoutError,
    TactDeformError,
    TransportError,
)
from tactdeform_hw.protocol.constants import BAUD_RATE
from tactdeform_hw.protocol.firmware import FirmwareSpec
from tactdeform_hw.protocol.units import DEFAULT_TRANSFER, CurrentTransfer

DEFAULT_TIMEOUT_S = 0.5


class SerialLike(Protocol):
    """What the driver uses of a pyserial ``Serial``."""

    is_open: bool
    timeout: float | None

    def open(self) -> None: ...
    def close(self) -> None: ...
    def write(self, data: bytes) -> int | None: ...
    def read(self, size: int = 1) -> bytes: ...
    def reset_input_buffer(self) -> None: ...


def _serial_error_types() -> tuple[type[BaseException], ...]:
    import serial

    return (serial.SerialException, OSError)


def _lower_lines(port: SerialLike) -> None:
    """Set DTR and RTS low on an unopened port, so that opening it does not reset the board."""
    for line in ("dtr", "rts"):
        if hasattr(port, line):
            setattr(port, line, False)


_BUSY_ERRNOS = frozenset({errno.EWOULDBLOCK, errno.EAGAIN, errno.EBUSY, errno.EACCES})


_exclusive_port_class: type | None = None


def exclusive_port_class() -> type:
    """:class:`ExclusivePort`: pyserial's ``Serial`` that locks the port before its first byte and declares
    itself guardable (built on first use: pyserial is imported lazily)."""
    global _exclusive_port_class
    if _exclusive_port_class is not None:
        return _exclusive_port_class
    import serial

    if sys.platform == "win32":  # pragma: no cover - Windows opens a COM port for one program only anyway
        _exclusive_port_class = serial.Serial
        return _exclusive_port_class
    import fcntl
    import termios

    class ExclusivePort(serial.Serial):  # type: ignore[misc]  # pyserial ships no type information
        """A serial port opened by path, owned by one program at a time (see the module docstring)."""

        #: A guardian process can share this port (an inheritable file descriptor to a terminal).
        guardable = True

        def __init__(self, *args: Any, **kwargs: Any) -> None:
            kwargs["exclusive"] = True
            super().__init__(*args, **kwargs)

        def open(self) -> None:
            try:
                super().open()
            except serial.SerialException as exc:
                if getattr(exc, "errno", None) in _BUSY_ERRNOS:
                    raise DeviceBusyError(str(self.port), find_holders(str(self.port)), str(exc)) from exc
                raise
            try:
                fcntl.ioctl(self.fd, termios.TIOCEXCL)
            except OSError:  # not a terminal: the flock alone guards it
                pass

        def close(self) -> None:
            fd = getattr(self, "fd", None)
            if self.is_open and fd is not None:
                try:
                    fcntl.ioctl(fd, termios.TIOCNXCL)  # the next owner may open it (a pty outlives us)
                except OSError:
                    pass
            super().close()

    _exclusive_port_class = ExclusivePort
    return ExclusivePort


#: What ``firmware=`` accepts: "auto" drives the version the board proves; a version drives only that one.
FIRMWARE_CHOICES = ("auto", "v1.2", "v2")


def check_firmware_choice(firmware: object) -> str:
    """``firmware`` as given, or :class:`~tactdeform_hw.errors.ConfigurationError` naming the choices."""
    if not isinstance(firmware, str) or firmware not in FIRMWARE_CHOICES:
        from tactdeform_hw.errors import ConfigurationError

        raise ConfigurationError(
            f"firmware={firmware!r}: use 'auto' (drive the version the board proves) or 'v1.2' or 'v2' "
            "(drive that version only, after the board has proved it); a board is never driven in a "
            "version it has not proved"
        )
    return firmware


class EtactileKitDevice(Device):
    """``port`` may be opened or not; an unopened one gets DTR/RTS low before it is opened.

    The board is driven only in the firmware version it has proved by a reply only that version gives
    (:mod:`.firmware_probe`): the constructor identifies it first, unless ``probe`` already holds that
    proof for this port.  ``firmware``: "auto" drives whichever version answered; "v1.2" or "v2" refuses a
    board that proved the other (:class:`~.firmware_probe.FirmwareMismatchError`); a board that proves
    neither is refused (:class:`~.firmware_probe.UnidentifiedBoardError`, or
    :class:`~tactdeform_hw.errors.BoardBusyError` on a port that serves one client at a time) after only
    bytes that stop current on both versions.

    ``guardian`` starts a guardian process with the device (default: when the port declares itself
    ``guardable``); a port that cannot be guarded with ``guardian=True`` is refused."""

    def __init__(
        self,
        port: SerialLike,
        *,
        mapping: ChannelMapping | None = None,
        transfer: CurrentTransfer = DEFAULT_TRANSFER,
        guard: SafetyGuard | None = None,
        pacer: Pacer | None = None,
        audit: AuditLog | None = None,
        guardian: bool | None = None,
        offline_clock: Clock | None = None,
        firmware: str = "auto",
        probe: Detection | None = None,
        settle_s: float | None = None,
    ) -> None:
        check_firmware_choice(firmware)
        self._settle_s = settle_s
        super().__init__(mapping=mapping, transfer=transfer, guard=guard, pacer=pacer, audit=audit)
        self.port = port
        self._errors = _serial_error_types()
        self._guardian: Guardian | None = None
        if not port.is_open:
            self._open_port()
        _no_delay(port)
        if pacer is None:  # what a port needs is known only once it is open (a URL builds its device then)
            self.pacer = default_pacer(port)
            if offline_clock is not None and getattr(port, "instant", False):
                # a port that answers at once (the in-process emulator) runs the session on the caller's clock
                self.pacer = Pacer(clock=offline_clock, policy=self.pacer.policy)
        if probe is None:
            probe = self._identify()
        # the identification wrote before anything else: its bytes are this device's own
        self.pacer.stats.bytes_written += probe.bytes_sent
        if self.audit is not None:
            self.audit.event(
                "firmware_probe",
                firmware=probe.name,
                attempts=probe.attempts,
                bytes=probe.bytes_sent,
                reply=probe.reply.hex(),
                settle_s=probe.settle_s,
            )
        self.identification = probe
        if firmware != "auto" and probe.name != firmware:
            self._refuse()
            check_firmware(firmware, probe, self._port_name())
        self._want_guardian = bool(getattr(port, "guardable", False)) if guardian is None else guardian
        if self._want_guardian:
            try:
                self._start_guardian()
            except BaseException:
                self._closed = True
                self._close_transport()
                raise
        self.speak(probe.firmware)
        try:
            self._open_proof()
        except FirmwareMismatchError:
            self._closed = True  # the board answered as another firmware: stopped, refused, released
            g, self._guardian = self._guardian, None
            if g is not None:
                g.release()
            self._close_transport()
            raise  # a board in an unknown state: nothing is sent before it proves its parser
        from tactdeform_hw.device.safety.failsafe import adopt

        adopt(self)  # a command's stop session watches every device opened under it

    def speak(self, firmware: FirmwareSpec) -> None:
        """:meth:`Device.speak`, and the guardian's stop for that firmware (v1.2's own stop would complete a
        v2 pattern in progress with 0xFB as a height's high byte)."""
        super().speak(firmware)
        stop = self.dialect.guardian_open_stop()
        if stop is not None and self._guardian is not None:
            self._guardian.set_stop(stop)

    def _refuse(self) -> None:
        """Give up a board before driving it: the port is closed, nothing more is written."""
        self._closed = True
        self._close_transport()

    def _identify(self) -> Detection:
        """Prove which firmware runs the board (see :mod:`.firmware_probe`); refuse it otherwise."""
        from tactdeform_hw.errors import BoardBusyError
        from tactdeform_hw.ports import board_untouched, serves_one_client

        name = self._port_name()
        audit = self.audit
        self.link.unproved_since = self.pacer.clock.now()

        def write(data: bytes) -> None:  # the identification's bytes are in the audit log like any other
            self._write(data)
            if audit is not None:
                audit.tx(data, t=self.pacer.clock.now(), op="identify", logical=data)

        settle_s = self._settle_s
        if settle_s is None:
            settle_s = 0.0 if board_untouched(self.port) else SETTLE_S

        def identify(wait_s: float) -> Detection:
            return detect_firmware(
                write,
                self._read,
                self._discard_input,
                device=name,
                settle_s=wait_s,
                sleep=self.pacer.clock.sleep,
            )

        try:
            try:
                return identify(settle_s)
            except UnidentifiedBoardError as silent:
                # a hung or locked board answers nothing and may still be stimulating: the reset line brings
                # it to its power-on state (every height 0, no command pending), and it is asked again
                if silent.reply or not self._can_reset() or not self._reset_transport():
                    raise
                if audit is not None:
                    audit.event("identification_reset", why="no answer to the identification")
                self.pacer.clock.sleep(self.boot_s)
                return identify(0.0)
        except UnidentifiedBoardError as exc:
            self._refuse()
            if serves_one_client(self.port) and not exc.reply:
                waited = settle_s + 2 * (float(getattr(self.port, "timeout", None) or 0.0) + 0.1)
                raise BoardBusyError(name, waited) from exc
            raise
        except BaseException:
            self._refuse()
            raise

    def _port_name(self) -> str:
        port = self.port
        return str(getattr(port, "port", None) or getattr(port, "name", None) or type(port).__name__)

    def _open_port(self) -> None:
        port = self.port
        _lower_lines(port)
        if getattr(port, "exclusive", False) is None:  # a pyserial port left at its default: lock it too
            port.exclusive = True  # type: ignore[attr-defined]
        try:
            port.open()
        except self._errors as exc:
            self._closed = True
            name = str(getattr(port, "port", port))
            if getattr(exc, "errno", None) in _BUSY_ERRNOS:
                raise DeviceBusyError(name, find_holders(name), str(exc)) from exc
            raise TransportError(f"cannot open {name}: {exc}") from exc
        except TactDeformError:
            self._closed = True
            raise

    @property
    def guardian(self) -> Guardian | None:
        """The guardian process watching this device's owner (None on a port that cannot be guarded)."""
        return self._guardian

    def _start_guardian(self) -> None:
        """A port that provides a guardian factory (``start_guardian(name)``: a USB port, whose claim
        cannot be shared) starts its own; any other guardable port shares its file descriptor with
        :meth:`Guardian.start`."""
        if not getattr(self.port, "guardable", False):
            raise TransportError(
                f"{self!r}: the port cannot be guarded (it declares no guardable file descriptor)"
            )
        factory = getattr(self.port, "start_guardian", None)
        name = str(getattr(self.port, "port", None) or getattr(self.port, "name", None) or self.port)
        try:
            if callable(factory):
                self._guardian = factory(name)
            else:
                try:
                    fd = int(self.port.fileno())  # type: ignore[attr-defined]
                except (AttributeError, OSError, ValueError, TypeError) as exc:
                    raise TransportError(
                        f"{self!r}: no file descriptor to share with a guardian: {exc}"
                    ) from exc
                # a port without a reset line says so (TCP); one that says nothing is a terminal with RTS
                reset_line = bool(getattr(self.port, "reset_line", True))
                self._guardian = Guardian.start(fd, name, reset_line=reset_line)
        except GuardianError as exc:
            raise TransportError(str(exc)) from exc
        self._tell_guardian()

    def _tell_guardian(self) -> None:
        g, cfg = self._guardian, self.config
        if g is None or cfg is None:
            return
        drain_s, zeros_s = pace_for(
            cfg.rate_hz, cfg.electrode_count, cfg.pulse_width_us, cfg.discharge_us, cfg.sense_width_us
        )
        g.configure(self.dialect.guardian_stop(cfg.electrode_count), drain_s, zeros_s)

    def configure(self, config: StimConfig) -> None:
        super().configure(config)
        self._tell_guardian()

    def close(self) -> None:
        """All channels off, then release the port; the guardian is let go only after that all-off
        succeeded — otherwise it switches the board off itself before it exits."""
        done = False
        try:
            super().close()
            done = True
        finally:
            g, self._guardian = self._guardian, None
            if g is not None:
                if done:
                    g.release()
                else:
                    g.abandon()

    def _write(self, data: bytes) -> None:
        try:
            written = self.port.write(data)
        except self._errors as exc:
            if type(exc).__name__ == "SerialTimeoutException":
                raise DeviceTimeoutError(f"write of {len(data)} byte(s) timed out") from exc
            raise DeviceGoneError(f"write failed: {exc}") from exc
        if written is not None and written != len(data):
            raise DeviceTimeoutError(f"wrote {written} of {len(data)} byte(s)")

    def _read(self, size: int) -> bytes:
        try:
            return bytes(self.port.read(size))
        except self._errors as exc:
            raise DeviceGoneError(f"read failed: {exc}") from exc

    def _waiting(self) -> int | None:
        try:
            waiting = getattr(self.port, "in_waiting", None)
        except self._errors as exc:
            raise DeviceGoneError(f"cannot poll input: {exc}") from exc
        return waiting if isinstance(waiting, int) else None

    def _discard_input(self) -> None:
        try:
            self.port.reset_input_buffer()
        except self._errors as exc:
            raise DeviceGoneError(f"cannot flush input: {exc}") from exc

    def _reopen_transport(self) -> None:
        # the guardian shares the old descriptor (and its lock): let it try to switch off through it,
        # then start a new one on the new descriptor
        g, self._guardian = self._guardian, None
        if g is not None:
            g.abandon()
        try:
            self.port.close()
        except self._errors:
            pass
        _lower_lines(self.port)
        try:
            self.port.open()
        except self._errors as exc:
            raise DeviceGoneError(f"cannot reopen {getattr(self.port, 'port', self.port)!s}: {exc}") from exc
        if self._want_guardian:
            self._start_guardian()

    def _can_reset(self) -> bool:
        if not getattr(self.port, "reset_line", True):  # the port says it has none (TCP)
            return False
        if callable(getattr(self.port, "pulse_reset", None)):
            return True
        return hasattr(self.port, "rts") and hasattr(self.port, "dtr")

    def _reset_transport(self) -> bool:
        """A port that models the reset line declares ``pulse_reset`` (every emulated board does); a
        real ESP32-S3 on its USB Serial/JTAG port is held in reset while RTS is asserted with DTR released
        (the sequence esptool uses), so the pulse is RTS high for 100 ms."""
        if not self._can_reset():
            return False
        pulse = getattr(self.port, "pulse_reset", None)
        if callable(pulse):
            try:
                pulse()
            except self._errors as exc:
                raise DeviceGoneError(f"cannot pulse the reset line: {exc}") from exc
            return True
        if not (hasattr(self.port, "rts") and hasattr(self.port, "dtr")):
            return False
        try:
            self.port.dtr = False
            self.port.rts = True
            self.pacer.clock.sleep(0.1)
            self.port.rts = False
        except self._errors as exc:
            raise DeviceGoneError(f"cannot pulse the reset line: {exc}") from exc
        return True

    def _close_transport(self) -> None:
        try:
            self.port.close()
        except self._errors:
            pass

    def __repr__(self) -> str:
        name = (
            getattr(self.port, "port", None) or getattr(self.port, "name", None) or type(self.port).__name__
        )
        return f"EtactileKitDevice({name!s}, closed={self._closed})"


def _no_delay(port: Any) -> None:
    """pyserial's ``socket://`` leaves Nagle's algorithm on: a one-byte request written after a small
    command then waits for the board's delayed acknowledgement (about 40 ms), longer than any reply's
    deadline.  The board's TCP server sets no delay too; so does the kit's own host library."""
    sock = getattr(port, "_socket", None)
    if sock is None:
        return
    import socket

    try:
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
    except OSError:  # not a TCP socket
        pass


def open_port(name: str, *, timeout: float = DEFAULT_TIMEOUT_S, baudrate: int = BAUD_RATE) -> Any:
    """An unopened pyserial port for a path, a URL, or ``emulator`` (the in-process emulator); or a
    pyserial-compatible USB port for ``usb://VID:PID[:SERIAL]`` (pyusb, no serial driver) and
    ``usb-emulator`` (the emulated board behind an emulated USB bus).  The scheme picks the transport
    from :mod:`tactdeform_hw.transports`, which other packages extend."""
    from tactdeform_hw.transports import port_for_name

    return port_for_name(name, timeout=timeout, baudrate=baudrate)


def open_serial_path(name: str, *, timeout: float | None, baudrate: int) -> Any:
    """A serial port path as an unopened :func:`exclusive_port_class` port (locked on open, guardable)."""
    import serial

    try:
        port = exclusive_port_class()(port=None, baudrate=baudrate, timeout=timeout, write_timeout=timeout)
        port.port = name
    except (serial.SerialException, ValueError) as exc:
        raise TransportError(f"cannot create port {name!r}: {exc}") from exc
    return port


def open_kit_url(name: str, *, timeout: float | None, baudrate: int) -> Any:
    """``etactilekit://ID[?discovery=HOST:PORT]``: the ``socket://`` port of the kit discovery finds."""
    from tactdeform_hw.transports import open_pyserial_url

    return open_pyserial_url(_resolve_kit(name), timeout=timeout, baudrate=baudrate)


def _resolve_kit(url: str) -> str:
    """``etactilekit://ID[?discovery=HOST:PORT]`` → the ``socket://IP:PORT`` of the one kit that answers
    UDP discovery with that id (default: the subnet broadcast on 8888)."""
    import urllib.parse as urlparse

    from tactdeform_hw.device.driver.wifi_discovery import DISCOVERY_PORT, discover, resolve
    from tactdeform_hw.errors import ConfigurationError

    parts = urlparse.urlsplit(url)
    kit_id = (parts.netloc + parts.path).strip("/")
    if not kit_id:
        raise ConfigurationError(f"{url!r}: expected etactilekit://ID (the id discovery reports)")
    query = urlparse.parse_qs(parts.query)
    target = ("255.255.255.255", DISCOVERY_PORT)
    if "discovery" in query:
        host, _, port = query["discovery"][-1].rpartition(":")
        try:
            target = (host or "127.0.0.1", int(port))
        except ValueError as exc:
            raise ConfigurationError(
                f"{url!r}: discovery={query['discovery'][-1]!r} is not HOST:PORT"
            ) from exc
    unknown = set(query) - {"discovery"}
    if unknown:
        raise ConfigurationError(
            f"{url!r}: unknown option(s) {', '.join(sorted(unknown))} (known: discovery)"
        )
    return resolve(kit_id, discover([target])).url


def open_device(
    name: str = "emulator",
    *,
    timeout: float = DEFAULT_TIMEOUT_S,
    mapping: ChannelMapping | None = None,
    transfer: CurrentTransfer = DEFAULT_TRANSFER,
    guard: SafetyGuard | None = None,
    pacer: Pacer | None = None,
    audit: AuditLog | None = None,
    guardian: bool | None = None,
    offline_clock: Clock | None = None,
    firmware: str = "auto",
    settle_s: float | None = None,
) -> EtactileKitDevice:
    """Open a device by name: a serial port path, a pyserial URL, ``usb:VID:PID[:SERIAL]``,
    ``usb-emulator``, or ``emulator`` (the default).  ``pacer`` defaults to what the port needs (see
    :func:`~tactdeform_hw.device.driver.pacing.default_pacer`); ``audit`` enables the session's audit log.  A
    port path is locked for this program alone (:class:`~tactdeform_hw.errors.DeviceBusyError` if another
    holds it) and gets a guardian process (``guardian=False`` to do without).  ``offline_clock``: when the
    port declares itself ``instant`` (it answers every byte at once), pace on this clock instead of the wall
    clock, so an offline run keeps session time.

    ``firmware``: "auto" (the default) drives the version the board proves; "v1.2" or "v2" drives only
    that version and refuses a board that proves the other.  Either way the board is identified first
    (:mod:`.firmware_probe`: v2's command timeout waited out, every current off, then a reply only one
    version gives); silence, a busy board or an answer neither version gives is a refusal naming the
    device, never a default.  Every refusal is a
    :class:`~tactdeform_hw.device.driver.firmware_probe.FirmwareMismatchError` (or, on a board that serves one
    client at a time, :class:`~tactdeform_hw.errors.BoardBusyError`), raised after only bytes that stop
    current on both versions.

    ``settle_s``: how long nothing is written before the identification (default:
    :data:`~.firmware_probe.SETTLE_S`, v2's command timeout and a margin, or 0 on a port that declares its
    board untouched since power-on).  Shorter is safe only when no other program can have written to the
    board since its power-on or since a session that ended with a proved ``close``: a v2 pattern an
    earlier program left cut would otherwise be completed, its heights with it."""
    check_firmware_choice(firmware)
    if guard is not None:
        # calibrated limits bind hardware channels: a mapping that wires an electrode elsewhere is refused
        # before the port is opened
        guard.check_wiring(mapping)
    port = open_port(name, timeout=timeout)
    return EtactileKitDevice(
        port,
        mapping=mapping,
        transfer=transfer,
        guard=guard,
        pacer=pacer,
        audit=audit,
        guardian=guardian,
        offline_clock=offline_clock,
        firmware=firmware,
        settle_s=settle_s,
    )
