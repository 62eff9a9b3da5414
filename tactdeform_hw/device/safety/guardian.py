"""The guardian: a second process that switches the board off when its owner dies without running code.

The firmware scans its last pattern at its last height until told otherwise, and a process killed with
SIGKILL, or one that crashes in native code, runs no handler, no ``finally`` and no ``atexit``.  So every
device opened on a port that can be guarded (``port.guardable``)
starts a guardian with it — a serial port opened by path, and a board's TCP connection (``socket://``,
the Wi-Fi build):

* it **shares the port**: it inherits the owner's open file descriptor, so it holds the same open file
  description — and therefore the same ``flock`` — as the owner.  No other program can take the board
  between the owner's death and the guardian's all-off, and the lock is released only when both are done.
  On TCP the shared socket keeps the connection open the same way: the board serves one client at a time,
  so a later client waits in its listen backlog until the guardian has switched the board off and left;
* it runs **in its own session** (``setsid``) and ignores SIGINT, SIGHUP and SIGQUIT, so a terminal's
  Ctrl-C or hang-up, delivered to the owner's whole process group, cannot stop it first;
* it **watches its owner through a pipe**: the owner holds the only write end, so end-of-file on the pipe
  means the owner is gone, however it went (the kernel closes a dead process's descriptors).  A clean
  close says ``bye`` first, after the owner's own all-off, and the guardian exits without writing;
* it knows **nothing of the protocol**: the owner hands it the bytes to send (``stop``: the packet that
  stops every current, ``off``: the all-off pattern for the configuration in force) and it sends them.

What the owner sends it is built by :func:`stop_packet` and :func:`off_packet` for firmware v1.2.  The
guardian does not know what the parser was doing when the owner died — it may be in the middle of any
command, and the device's 256-byte queue may be full, in which case the firmware discards the rest of
the USB packet at the first byte that does not fit.  So the stop packet is built to be safe **at every
entry point and under every tail loss**:

* it starts with eight zeros: a u8 or u16 command the owner left half-received is finished with zeros
  (a zero height, a zero width or frequency, which the firmware ignores, an electrode count of 0 — the
  guardian never sends a pattern before it has proof, so that cannot lock the parser);
* every command in it (pulse height 0, sense height 0, each twice) has an all-zero payload and is followed
  by zeros, so a command whose payload was cut by a lost tail is finished with zeros by the next packet,
  which again starts with zeros — never with a command byte that would become a height's high byte;
* a command byte read as part of a pattern the owner left half-received is a pattern value other than
  1 and 2, which the firmware treats as off;
* it ends with the HV513 count request: its one-byte reply proves that the packet reached the queue up to
  its last byte (a loss only ever removes a tail) and that the parser has read it — the heights are 0.

**Paced for the 256-byte queue.**  Before its first byte the guardian waits until what the owner left
in the queue has surely been read (``drain_s``: the owner's pacer spaces payload commands so that only a
few are ever in flight; the owner tells the guardian that bound for its configuration).  Over USB the
packet is safe even into a full queue (above); over a UART, where a full queue drops single bytes and
keeps later ones, no byte sequence but zeros is safe, so there the wait is what keeps every byte in.
Without the proof the guardian sends 256 zeros (in 64-byte packets), waits until the parser has surely
skipped them (``zeros_s``, also from the owner), and sends the packet again, for up to :data:`BUDGET_S`; with
the proof it sends the all-off pattern (electrode count, then the pattern, then another proof).  Pulse height
0 and sense height 0 already stop every current the firmware can deliver, whatever pattern it holds; the
pattern is there so that a later height cannot reach an old pattern.  If no proof ever comes (a locked parser
answers nothing) and the owner said the port has a reset line, the guardian pulses it (RTS, as the driver
does), which brings the firmware back to its power-on state: every height 0.

**On a socket** (TCP) the guardian finds a socket behind its descriptor and adapts what is terminal-only:

* what the owner left in the kernel's send queue **cannot be recalled** (there is no ``TCOFLUSH``): it
  reaches the board whole and in order, a command the owner cut included, ahead of anything the guardian
  sends.  So the stop packet goes **at once**, right behind it: it is built to be safe wherever the parser
  enters it, and TCP loses no tail (the Wi-Fi build reads the stream under flow control), so it can only
  finish the owner's cut command with zeros and command bytes (pattern values that are off) and then stop
  the currents — or, when a long cut pattern swallows it, be followed by the proof loop's copies;
* the **drain wait** is then not needed to keep bytes in (nothing is dropped) but to keep the owner's
  stale replies from being taken as the proof: the guardian waits until its send queue is empty
  (``SIOCOUTQ``: the board's stack has acknowledged every byte), then ``drain_s`` for the board to read
  them, then reads and drops what is waiting (there is no ``TCIFLUSH``), and sends the stop again for the
  proof.  A late reply to the first copy proves what matters as well: the parser was at a command
  boundary before the second copy, which is already on its way and cannot be lost, so its heights 0 are
  read next, before anything the guardian sends after the proof;
* there is **no reset line** on TCP (RTS and DTR do not travel): the port declares ``reset_line = False``
  and the guardian never tries.

The guardian is started with ``python -I -S`` on this very file: it imports nothing but the standard
library, so it is ready in tens of milliseconds, and nothing it imports can fail.
"""

from __future__ import annotations

import os
import select
import signal
import stat
import sys
import time
from collections.abc import Callable
from typing import TYPE_CHECKING, Any, Protocol

if TYPE_CHECKING:
    import argparse

#: How long the guardian keeps trying to get a proof before it gives up (or pulses the reset line).
BUDGET_S = 1.0
#: Leading and separating zeros of the stop packet (see the module docstring).
LEAD_ZEROS = 8
GAP_ZEROS = 4
#: Zeros that finish any command in progress (a pattern of up to 255 channels) — the resync run.
RESYNC_ZEROS = 256
#: A USB full-speed bulk packet: what the firmware moves into its queue, or discards the tail of, at once.
PACKET_BYTES = 64
#: Pacing when the owner has not said (no configuration yet): a 100 Hz alarm whose scan may starve the
#: parser to one payload command per period, four of them in flight; 256 zeros at 50 µs of parser time
#: per period (see :mod:`.pacing`).
DEFAULT_DRAIN_S = 0.045
DEFAULT_ZEROS_S = 0.2


# --- the bytes (owner side: built with the protocol module) -------------------------------------------------


def stop_packet() -> bytes:
    """Zeros, pulse height 0 twice, sense height 0 twice, each followed by zeros, and a proof request."""
    from tactdeform_hw import protocol as p

    z = bytes(GAP_ZEROS)
    height0, sense0 = p.encode_pulse_height(0), p.encode_sense_height(0)
    data = bytes(LEAD_ZEROS) + height0 + z + height0 + z + sense0 + z + sense0 + z + p.HV513_COUNT_REQUEST
    assert len(data) <= PACKET_BYTES
    return data


def off_packet(electrode_count: int) -> bytes:
    """Zeros, the electrode count (then itself again, or a zero where it would look like a command
    byte: a lost count is then read as the same count or as 0), zeros, the all-off pattern, zeros, a proof
    request.  Sent only after a proof that the parser is in step; the count comes first because a zero of
    the resync may have set it to 0, and a pattern then would lock the parser."""
    from tactdeform_hw import protocol as p
    from tactdeform_hw.device.driver.pacing import COMMAND_BYTE_MIN

    n = int(electrode_count)
    count = p.encode_electrode_num(n)
    echo = bytes([n]) if n < COMMAND_BYTE_MIN else b"\x00"
    return (
        bytes(LEAD_ZEROS)
        + count
        + echo
        + bytes(GAP_ZEROS)
        + p.encode_pattern(bytes(n), electrode_num=n)
        + bytes(GAP_ZEROS)
        + p.HV513_COUNT_REQUEST
    )


def pace_for(
    rate_hz: int, electrode_count: int, pulse_width_us: int, discharge_us: int, sense_width_us: int
) -> tuple[float, float]:
    """``(drain_s, zeros_s)`` for a configuration: how long the firmware may need to read what the owner's
    pacer left in flight (four payload commands at the pace of the longest scan the guard allows), and to
    skip 256 zeros at that scan."""
    from tactdeform_hw.device.driver.pacing import (
        SCAN_GAP_MIN_US,
        Pacer,
        estimate_scan_us,
        firmware_period_us,
    )

    period_us = firmware_period_us(rate_hz)
    full = estimate_scan_us(bytes([2]) * electrode_count, pulse_width_us, discharge_us, sense_width_us)
    scan_us = min(full, period_us - SCAN_GAP_MIN_US)
    pacer = Pacer()
    pacer.set_timing(period_us / 1e6, scan_us / 1e6)
    drain_s = 4 * pacer.payload_interval_s() + pacer.policy.link_latency_s + pacer.policy.tick_s
    return drain_s, pacer.skip_s(RESYNC_ZEROS)


def zeros_gap_s(zeros_s: float) -> float:
    """The wait after each packet of a retry's zeros: the time the firmware needs to skip one packet of
    them (``zeros_s`` is its time for all :data:`RESYNC_ZEROS`).  Its parser reads only between scans, so
    packets sent faster than that pile up in the receive queue, and the queue discards what does not fit."""
    return max(0.0012, zeros_s * PACKET_BYTES / RESYNC_ZEROS)


# --- owner side --------------------------------------------------------------------------------------------


class GuardianError(Exception):
    """The guardian could not be started (raised as a TransportError by the driver)."""


class Guardian:
    """The owner's handle on its guardian process.  :meth:`start` spawns it; :meth:`configure` tells it
    the all-off pattern of the configuration in force; :meth:`release` (after the owner's own all-off)
    lets it go without writing; :meth:`abandon` closes the pipe without ``bye``, as a dead owner would,
    so the guardian switches the board off."""

    def __init__(
        self, proc: Any, pipe_w: int, name: str, release_owner: Callable[[], None] | None = None
    ) -> None:
        self.proc = proc
        self._pipe_w: int | None = pipe_w
        self.name = name
        #: what the owner lets go of before it abandons the board to the guardian (a USB claim, which
        #: cannot be shared: the guardian can take the board only once the owner released it)
        self._release_owner = release_owner

    @property
    def pid(self) -> int:
        return int(self.proc.pid)

    @classmethod
    def start(
        cls,
        port_fd: int,
        name: str,
        *,
        stop: bytes | None = None,
        reset_line: bool = False,
        ready_timeout_s: float = 10.0,
    ) -> Guardian:
        """Spawn the guardian on ``port_fd`` (the owner's open port) and wait until it is watching."""
        stop = stop_packet() if stop is None else stop
        cmd = [sys.executable, "-I", "-S", os.path.abspath(__file__), "--port-fd", str(port_fd)]
        cmd += ["--name", name, "--stop", stop.hex()] + (["--reset-line"] if reset_line else [])
        return cls.spawn(cmd, name, pass_fds=(port_fd,), ready_timeout_s=ready_timeout_s)

    @classmethod
    def spawn(
        cls,
        cmd: list[str],
        name: str,
        *,
        pass_fds: tuple[int, ...] = (),
        ready_timeout_s: float = 10.0,
        release_owner: Callable[[], None] | None = None,
    ) -> Guardian:
        """Start a guardian process ``cmd`` (given ``--owner-fd`` and ``--owner-pid``) in its own session
        and wait until it says ``ready``: what every kind of guardian shares."""
        import subprocess

        r, w = os.pipe()  # both ends close-on-exec: only the guardian gets the read end, nobody the write end
        cmd = [*cmd, "--owner-fd", str(r), "--owner-pid", str(os.getpid())]
        try:
            proc = subprocess.Popen(
                cmd,
                pass_fds=(*pass_fds, r),
                stdin=subprocess.DEVNULL,
                stdout=subprocess.PIPE,
                start_new_session=True,
                close_fds=True,
            )
        except OSError as exc:
            os.close(r)
            os.close(w)
            raise GuardianError(f"cannot start the guardian for {name}: {exc}") from exc
        os.close(r)
        g = cls(proc, w, name, release_owner)
        out = proc.stdout
        assert out is not None
        ready, _, _ = select.select([out], [], [], ready_timeout_s)
        line = out.readline() if ready else b""
        out.close()
        if line.strip() != b"ready":
            g.close_pipe()
            proc.kill()
            proc.wait()
            raise GuardianError(f"the guardian for {name} did not start (it said {line!r})")
        return g

    def tell(self, *words: str) -> bool:
        """One line to the guardian; False if it is gone (it was killed, or already acted)."""
        if self._pipe_w is None:
            return False
        try:
            os.write(self._pipe_w, (" ".join(words) + "\n").encode("ascii"))
        except OSError:
            return False
        return True

    def set_stop(self, packet: bytes) -> bool:
        return self.tell("stop", packet.hex())

    def configure(
        self, off: bytes | None, drain_s: float | None = None, zeros_s: float | None = None
    ) -> bool:
        """The all-off pattern for the configuration in force (None: unknown, heights only), and how
        long the firmware may need to read what the owner left in its queue, and to skip 256 zeros."""
        ok = self.tell("off", off.hex() if off else "-")
        if drain_s is not None and zeros_s is not None:
            ok = self.tell("pace", f"{drain_s:.6f}", f"{zeros_s:.6f}") and ok
        return ok

    @property
    def alive(self) -> bool:
        return self._pipe_w is not None and self.proc.poll() is None

    def release(self, timeout_s: float = 5.0) -> None:
        """The owner switched everything off itself: the guardian exits without writing."""
        self.tell("bye")
        self.close_pipe()
        self._wait(timeout_s)

    def abandon(self, timeout_s: float = 5.0) -> None:
        """The owner could not switch off (or does not know): the guardian does it, and the call waits for
        it, so the port is free when this returns."""
        release, self._release_owner = self._release_owner, None
        if release is not None and self._pipe_w is not None:
            release()
        self.close_pipe()
        self._wait(timeout_s)

    def close_pipe(self) -> None:
        """Close the owner's end of the pipe to the guardian (after "bye" it exits; without it, it acts)."""
        if self._pipe_w is not None:
            try:
                os.close(self._pipe_w)
            finally:
                self._pipe_w = None

    def _wait(self, timeout_s: float) -> None:
        import subprocess

        try:
            self.proc.wait(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()


def start_guardian(port: Any, who: str) -> Guardian:
    """The guardian of a device's port (``who``: the device, in errors).  A port that provides a guardian
    factory (``start_guardian(name)``: a USB port, whose claim cannot be shared) starts its own; any other
    guardable port shares its file descriptor with :meth:`Guardian.start`.  A port that cannot be guarded
    raises :class:`~tactdeform_hw.errors.TransportError`."""
    from tactdeform_hw.errors import TransportError

    if not getattr(port, "guardable", False):
        raise TransportError(f"{who}: the port cannot be guarded (it declares no guardable file descriptor)")
    factory = getattr(port, "start_guardian", None)
    name = str(getattr(port, "port", None) or getattr(port, "name", None) or port)
    try:
        if callable(factory):
            return factory(name)  # type: ignore[no-any-return]
        try:
            fd = int(port.fileno())
        except (AttributeError, OSError, ValueError, TypeError) as exc:
            raise TransportError(f"{who}: no file descriptor to share with a guardian: {exc}") from exc
        # a port without a reset line says so (TCP); one that says nothing is a terminal with RTS
        reset_line = bool(getattr(port, "reset_line", True))
        return Guardian.start(fd, name, reset_line=reset_line)
    except GuardianError as exc:
        raise TransportError(str(exc)) from exc


# --- guardian side (stdlib only) ---------------------------------------------------------------------------


def say(name: str, msg: str) -> None:
    try:
        sys.stderr.write(f"tactdeform-hw guardian [{name}]: {msg}\n")
        sys.stderr.flush()
    except (OSError, ValueError):
        pass


def _write_all(fd: int, data: bytes, deadline: float) -> bool:
    view = memoryview(data)
    while view:
        left = deadline - time.monotonic()
        if left <= 0:
            return False
        try:
            _, ready, _ = select.select([], [fd], [], left)
            if not ready:
                continue
            n = os.write(fd, view)
        except (BlockingIOError, InterruptedError):
            continue
        except (OSError, ValueError):  # the port is gone (unplugged): nothing more can be sent
            return False
        view = view[n:]
    return True


def read_until_quiet(read: Callable[[float], bytes | None], timeout_s: float) -> bytes:
    """What the board answers within ``timeout_s``, read until it has been quiet for 3 ms: the one rule
    every link's ``read_reply`` follows.  ``read(left_s)`` returns what arrived within ``left_s`` (``b""``
    if nothing did) or None when the link is gone; a spurious wake-up (``BlockingIOError``,
    ``InterruptedError``) from it is retried."""
    got = b""
    deadline = time.monotonic() + timeout_s
    while True:
        left = deadline - time.monotonic()
        if got:
            left = min(left, 0.003)
        if left <= 0:
            return got
        try:
            chunk = read(left)
        except (BlockingIOError, InterruptedError):
            continue
        if chunk is None:
            return got
        if not chunk:
            if got:
                return got
            continue
        got += chunk


def _read_within(fd: int, timeout_s: float) -> bytes | None:
    """What ``fd`` holds within ``timeout_s`` (``b""``: nothing came); None once the port is gone."""
    try:
        ready, _, _ = select.select([fd], [], [], timeout_s)
        if not ready:
            return b""
        return os.read(fd, 4096) or None
    except (BlockingIOError, InterruptedError):
        raise  # a wake-up with nothing to read: the caller tries again
    except (OSError, ValueError):
        return None


def _read_reply(fd: int, timeout_s: float) -> bytes:
    """What the board answers within ``timeout_s``, read until it has been quiet for 3 ms."""
    return read_until_quiet(lambda left_s: _read_within(fd, left_s), timeout_s)


def _flush(fd: int, which: int) -> None:
    import termios

    try:
        termios.tcflush(fd, which)
    except (OSError, termios.error):
        pass


def _pulse_reset(fd: int) -> bool:
    """RTS high for 100 ms with DTR low: an ESP32-S3 held in reset, as the driver does it."""
    import fcntl
    import struct
    import termios

    try:
        fcntl.ioctl(fd, termios.TIOCMBIC, struct.pack("I", termios.TIOCM_DTR))
        fcntl.ioctl(fd, termios.TIOCMBIS, struct.pack("I", termios.TIOCM_RTS))
        time.sleep(0.1)
        fcntl.ioctl(fd, termios.TIOCMBIC, struct.pack("I", termios.TIOCM_RTS))
    except OSError:
        return False
    return True


def _is_socket(fd: int) -> bool:
    try:
        return stat.S_ISSOCK(os.fstat(fd).st_mode)
    except OSError:
        return False


def _discard_input(fd: int) -> None:
    """Read and drop what a socket holds (a socket has no ``tcflush``)."""
    while True:
        try:
            ready, _, _ = select.select([fd], [], [], 0)
            if not ready or not os.read(fd, 65536):
                return
        except (BlockingIOError, InterruptedError):
            return
        except (OSError, ValueError):
            return


def _wait_sent(fd: int, deadline: float) -> None:
    """Wait until the socket's send queue is empty (``SIOCOUTQ``: bytes not yet acknowledged by the
    board's TCP stack), or the deadline.  Where the query is not available, return at once."""
    import fcntl
    import struct
    import termios

    request = getattr(termios, "TIOCOUTQ", None)  # Linux: the same request as SIOCOUTQ on a socket
    if request is None:
        return
    while time.monotonic() < deadline:
        try:
            (left,) = struct.unpack("i", fcntl.ioctl(fd, request, struct.pack("i", 0)))
        except OSError:
            return
        if left <= 0:
            return
        time.sleep(0.002)


class GuardianLink(Protocol):
    """What :func:`switch_off_on` needs of the board's link: a serial port's descriptor
    (:class:`FdLink`) or a USB interface the guardian claimed (:mod:`.usb_guardian`)."""

    def discard_output(self) -> bool: ...
    def wait_sent(self, deadline: float) -> None: ...
    def discard_input(self) -> None: ...
    def write(self, data: bytes, deadline: float) -> bool: ...
    def read_reply(self, timeout_s: float) -> bytes: ...
    def pulse_reset(self) -> bool: ...


class FdLink:
    """The owner's serial port, through the descriptor the guardian inherited."""

    def __init__(self, fd: int) -> None:
        self.fd = fd

    def discard_output(self) -> bool:
        """Drop what the dead owner left unsent; False where that cannot be done (a socket)."""
        import termios

        _flush(self.fd, termios.TCOFLUSH)
        return True

    def wait_sent(self, deadline: float) -> None:
        return None  # a terminal's output was dropped, not sent

    def discard_input(self) -> None:
        import termios

        _flush(self.fd, termios.TCIFLUSH)

    def write(self, data: bytes, deadline: float) -> bool:
        return _write_all(self.fd, data, deadline)

    def read_reply(self, timeout_s: float) -> bytes:
        return _read_reply(self.fd, timeout_s)

    def pulse_reset(self) -> bool:
        return _pulse_reset(self.fd)


class SocketLink(FdLink):
    """The owner's TCP connection to the Wi-Fi board (see the module docstring): what the owner left in
    the send queue cannot be recalled and reaches the board whole and in order, so the stop follows it at
    once; there is no reset line and no ``tcflush``."""

    def discard_output(self) -> bool:
        return False

    def wait_sent(self, deadline: float) -> None:
        _wait_sent(self.fd, deadline)

    def discard_input(self) -> None:
        _discard_input(self.fd)

    def pulse_reset(self) -> bool:
        return False


def fd_link(fd: int) -> FdLink:
    """The link behind ``fd``: a socket (the Wi-Fi board's TCP connection) or a terminal."""
    return SocketLink(fd) if _is_socket(fd) else FdLink(fd)


def switch_off(fd: int, stop: bytes, off: bytes | None, **kwargs: Any) -> str:
    """Stop every current on the board behind ``fd``, a terminal or a socket (see :func:`switch_off_on`)."""
    return switch_off_on(fd_link(fd), stop, off, **kwargs)


def switch_off_on(
    link: GuardianLink,
    stop: bytes,
    off: bytes | None,
    *,
    reset_line: bool = False,
    budget_s: float = BUDGET_S,
    drain_s: float = DEFAULT_DRAIN_S,
    zeros_s: float = DEFAULT_ZEROS_S,
    name: str = "",
) -> str:
    """Stop every current on the board behind ``link``; returns how it was proved (for the message)."""
    t0 = time.monotonic()
    end = t0 + max(budget_s, drain_s + zeros_s + 0.1)
    if not link.discard_output():
        # what the owner left unsent cannot be recalled (TCP) and will reach the board whole and in
        # order: the stop goes at once, right behind it, and the drain wait below only keeps the owner's
        # stale replies from being taken as the proof
        if not link.write(stop, end):
            return "gave up: the connection does not take bytes"
        link.wait_sent(end)
    time.sleep(drain_s)  # what the owner left in the device's queue is read first (see the docstring)
    link.discard_input()  # its replies are stale
    wait_s = max(0.02, drain_s)
    attempt = 0
    while time.monotonic() < end:
        if attempt:
            # the packet, or its proof, was lost (a full queue) or swallowed by a half-received pattern:
            # finish whatever is in progress with zeros, a packet at a time as fast as the parser skips
            # them, and try again once they are skipped
            for _ in range(RESYNC_ZEROS // PACKET_BYTES):
                if not link.write(bytes(PACKET_BYTES), end):
                    return "gave up: the port does not take bytes"
                time.sleep(zeros_gap_s(zeros_s))
        attempt += 1
        if not link.write(stop, end):
            return "gave up: the port does not take bytes"
        reply = link.read_reply(min(wait_s, max(0.0, end - time.monotonic())))
        if reply:
            break
        wait_s = min(wait_s * 2, 0.2)
    else:
        if reset_line and link.pulse_reset():
            return "no answer from the firmware; its reset line was pulsed (power-on state: every height 0)"
        return "NO PROOF: the firmware did not answer; it may still be stimulating: unplug the board"
    how = f"heights 0 proved after {attempt} attempt(s) in {1000 * (time.monotonic() - t0):.1f} ms"
    if off:
        if link.write(off, time.monotonic() + 0.5) and link.read_reply(0.2):
            how += ", all-off pattern proved"
        else:
            how += ", all-off pattern not proved"
    return how


class Orders:
    """What the owner told its guardian before it went: the bytes to send and how to pace them."""

    def __init__(self, stop: bytes) -> None:
        self.stop = stop
        self.off: bytes | None = None
        self.drain_s = DEFAULT_DRAIN_S
        self.zeros_s = DEFAULT_ZEROS_S

    def carry_out(self, link: GuardianLink, *, reset_line: bool, name: str) -> str:
        """Stop every current on the board behind ``link`` with these bytes and this pacing
        (:func:`switch_off_on`); returns how it was proved."""
        return switch_off_on(
            link,
            self.stop,
            self.off,
            reset_line=reset_line,
            drain_s=self.drain_s,
            zeros_s=self.zeros_s,
            name=name,
        )


def ignore_terminal_signals() -> None:
    """A terminal's Ctrl-C, hang-up or stop keys reach the owner's process group, never the guardian."""
    for sig in (signal.SIGINT, signal.SIGHUP, signal.SIGQUIT, signal.SIGTSTP, signal.SIGTTOU, signal.SIGTTIN):
        signal.signal(sig, signal.SIG_IGN)
    signal.signal(signal.SIGPIPE, signal.SIG_IGN)
    try:
        os.chdir("/")  # hold no directory of the owner's
    except OSError:
        pass


def say_ready() -> None:
    sys.stdout.write("ready\n")
    sys.stdout.flush()
    sys.stdout.close()


def watch_owner(owner_fd: int, stop: bytes) -> Orders | None:
    """Read the owner's lines (``stop``, ``off``, ``pace``) until it says ``bye`` (None: nothing to do)
    or its end of the pipe closes — it is gone, however it went: the orders to carry out."""
    orders = Orders(stop)
    buf = b""
    while True:
        try:
            chunk = os.read(owner_fd, 4096)
        except InterruptedError:
            continue
        except OSError:
            chunk = b""
        if not chunk:
            return orders  # the owner is gone without saying bye
        buf += chunk
        while b"\n" in buf:
            line, buf = buf.split(b"\n", 1)
            words = line.decode("ascii", "replace").split()
            if not words:
                continue
            if words[0] == "bye":
                return None
            if words[0] == "stop" and len(words) == 2:
                orders.stop = bytes.fromhex(words[1])
            elif words[0] == "off" and len(words) == 2:
                orders.off = None if words[1] == "-" else bytes.fromhex(words[1])
            elif words[0] == "pace" and len(words) == 3:
                orders.drain_s, orders.zeros_s = min(float(words[1]), 0.5), min(float(words[2]), 0.5)


def add_owner_arguments(ap: argparse.ArgumentParser) -> None:
    """The options every kind of guardian is started with (see :meth:`Guardian.spawn`): the owner's pipe
    and pid, the board's name for messages, whether it has a reset line, and the first stop bytes."""
    ap.add_argument("--owner-fd", type=int, required=True)
    ap.add_argument("--owner-pid", type=int, default=0)
    ap.add_argument("--name", default="")
    ap.add_argument("--reset-line", action="store_true")
    ap.add_argument("--stop", required=True, help="hex bytes that stop every current")


def report_gone(name: str, owner_pid: int, how: str) -> int:
    """Say what was done for an owner gone without ``bye``; the exit status: 2 when the board was not
    proved off (the message then says to unplug it), else 0."""
    say(name, f"owner (pid {owner_pid}) gone: all-off sent ({how})")
    return 0 if not how.startswith(("NO PROOF", "gave up")) else 2


def main(argv: list[str]) -> int:
    import argparse

    ap = argparse.ArgumentParser(prog="tactdeform-hw-guardian")
    ap.add_argument("--port-fd", type=int, required=True)
    add_owner_arguments(ap)
    a = ap.parse_args(argv)
    ignore_terminal_signals()
    say_ready()
    orders = watch_owner(a.owner_fd, bytes.fromhex(a.stop))
    if orders is None:
        return 0
    how = orders.carry_out(fd_link(a.port_fd), reset_line=a.reset_line, name=a.name)
    return report_gone(a.name, a.owner_pid, how)


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
