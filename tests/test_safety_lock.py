"""One owner per board: a second program is refused before it writes a byte, and told who holds the board."""

from __future__ import annotations

import fcntl
import os
import signal
import struct
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
import serial

from tactdeform_hw.device import EtactileKitDevice, StimConfig, open_device
from tactdeform_hw.emulator.serving.pty_server import PtyServer
from tactdeform_hw.errors import DeviceBusyError, TransportError

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "tools"))
from stop_latency import BoardWatch  # noqa: E402

ENV = dict(os.environ, PYTHONPATH=str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", ""))
WAIT_S = 60.0
TIOCGEXCL = 0x80045440  # Linux: is the terminal in exclusive mode?


@pytest.fixture
def board() -> Iterator[tuple[PtyServer, BoardWatch]]:
    watch = BoardWatch()
    server = PtyServer(watch).start()  # type: ignore[arg-type]
    try:
        yield server, watch
    finally:
        server.stop()


def _exclusive_flag(path: str) -> int:
    fd = os.open(path, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)  # root may open an exclusive terminal
    try:
        return struct.unpack("i", fcntl.ioctl(fd, TIOCGEXCL, b"\0\0\0\0"))[0]
    finally:
        os.close(fd)


def test_a_second_open_in_the_same_program_is_refused_and_writes_nothing(
    board: tuple[PtyServer, BoardWatch],
) -> None:
    server, watch = board
    with open_device(server.path) as dev:
        dev.configure(StimConfig(current_ua=600))
        dev.send_pattern([1, 0] * 16)
        assert watch.wait(True, WAIT_S)
        before, state = watch.bytes_in, watch.state()
        with pytest.raises(DeviceBusyError) as exc:
            open_device(server.path)
        time.sleep(0.05)
        assert watch.bytes_in == before and watch.state() == state  # not one byte
        err = exc.value
        assert isinstance(err, TransportError) and err.device == server.path
        assert server.path in str(err) and "nothing was written" in str(err)
        assert (os.getpid(), err.holders[0][1]) == err.holders[0]  # the flock's holder comes first: us
        assert dev.guardian is not None and dev.guardian.pid in [pid for pid, _ in err.holders]
    with open_device(server.path, guardian=False) as again:  # released on close: the next owner gets it
        again.configure(StimConfig(current_ua=100))


def test_a_second_program_is_refused_with_the_holder_named(board: tuple[PtyServer, BoardWatch]) -> None:
    server, watch = board
    with open_device(server.path) as dev:
        dev.configure(StimConfig(current_ua=600))
        dev.send_pattern([1, 0] * 16)
        assert watch.wait(True, WAIT_S)
        before, state = watch.bytes_in, watch.state()
        proc = subprocess.run(
            [
                sys.executable,
                "-m",
                "tactdeform_hw.cli",
                "send",
                "--device",
                server.path,
                "--pattern",
                "all:1",
                "--current-ua",
                "2000",
            ],
            capture_output=True,
            text=True,
            env=ENV,
            cwd=str(REPO),
            timeout=WAIT_S,
        )
        assert proc.returncode == 1, proc.stderr
        line = proc.stderr.strip()
        assert line.startswith(
            f"tactdeform-hw send: error: {server.path} is in use by another program: pid {os.getpid()} ("
        )
        assert "nothing was written" in line and "Traceback" not in proc.stderr
        time.sleep(0.05)
        assert watch.bytes_in == before and watch.state() == state


def test_a_script_with_its_own_pyserial_port_is_locked_out_too(board: tuple[PtyServer, BoardWatch]) -> None:
    server, watch = board
    with open_device(server.path) as owner:
        port = serial.Serial(None, 921600, timeout=0.5)
        port.port = server.path
        written = owner.pacer.stats.bytes_written
        end = time.monotonic() + 30.0  # the server reads the owner's last bytes in its own thread
        while watch.bytes_in < written and time.monotonic() < end:
            time.sleep(0.005)
        before = watch.bytes_in
        assert before == written
        with pytest.raises(DeviceBusyError):
            EtactileKitDevice(port)
        assert watch.bytes_in == before
    port = serial.Serial(None, 921600, timeout=0.5)
    port.port = server.path
    dev = EtactileKitDevice(port)  # free again; a port the script built is locked the same way
    with pytest.raises(DeviceBusyError):
        open_device(server.path)
    dev.close()


def test_the_terminal_is_exclusive_while_owned_and_released_after(
    board: tuple[PtyServer, BoardWatch],
) -> None:
    server, _ = board
    assert _exclusive_flag(server.path) == 0
    with open_device(server.path, guardian=False):
        assert _exclusive_flag(server.path) == 1  # TIOCEXCL: anyone but root is refused at open()
    assert _exclusive_flag(server.path) == 0  # the pty outlives its client: the next owner can open it


OWNER = """
import sys, time
from tactdeform_hw.device import StimConfig, open_device
dev = open_device(sys.argv[1])
dev.configure(StimConfig(current_ua=1000))
dev.send_pattern([1, 0] * 16)
print("ready", flush=True)
time.sleep(600)
"""


def test_nobody_takes_the_board_before_the_guardian_switched_it_off(
    board: tuple[PtyServer, BoardWatch],
) -> None:
    """The guardian shares the owner's open file description, so the lock outlives a SIGKILLed owner
    until the all-off is on the wire: a program that opens the board then finds it off."""
    server, watch = board
    proc = subprocess.Popen(
        [sys.executable, "-c", OWNER, server.path],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=ENV,
        start_new_session=True,
    )
    try:
        assert proc.stdout is not None and proc.stdout.readline().strip() == "ready"
        assert watch.wait(True, WAIT_S)
        os.kill(proc.pid, signal.SIGKILL)
        end = time.monotonic() + WAIT_S
        while True:
            try:
                dev = open_device(server.path, guardian=False)
                break
            except DeviceBusyError:
                assert time.monotonic() < end
                time.sleep(0.001)
        try:
            assert not watch.on, watch.state()  # off before anyone else could open it
        finally:
            dev.close()
    finally:
        if proc.poll() is None:
            proc.kill()
        proc.communicate(timeout=WAIT_S)


def test_reconnect_keeps_one_owner_and_a_guardian_on_the_new_descriptor(
    board: tuple[PtyServer, BoardWatch],
) -> None:
    server, watch = board
    with open_device(server.path) as dev:
        dev.configure(StimConfig(current_ua=600))
        dev.send_pattern([1, 0] * 16)
        old = dev.guardian
        assert old is not None
        dev.reconnect()
        new = dev.guardian
        assert new is not None and new.pid != old.pid and old.proc.returncode is not None and new.alive
        with pytest.raises(DeviceBusyError):
            open_device(server.path)  # still ours
        dev.send_pattern([1, 0] * 16)
        assert watch.wait(True, WAIT_S) and dev.probe()
    assert new.proc.returncode == 0 and not watch.on
