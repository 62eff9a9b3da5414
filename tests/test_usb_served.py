"""One owner per board over USB, and a stop when the owner dies without running code.

The board is served by ``tactdeform-hw emulate --usb`` in its own process, as a board sits on a bus: it
outlives the programs that use it and every program sees the same one.  Programs open it by the name the
command prints (``usb-emulator://PATH``) through pyusb.  Every verdict is on the board's delivered-pulse
record (``board_status``: the last pulse that carried current) or on what the server saw each client
write, never on what a host meant to send.  The detach refusal runs on the in-process emulated bus with a
fake sysfs tree (there is no real hardware here).
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

pytest.importorskip("usb.core")

from tactdeform_hw.device.driver.usb_transport import UsbCdcPort  # noqa: E402
from tactdeform_hw.emulator.serving.usb_backend import EmulatedUsbBackend, EmulatedUsbDevice  # noqa: E402
from tactdeform_hw.emulator.serving.usb_client import SERVED_PREFIX, EmulatorClientBackend  # noqa: E402
from tactdeform_hw.errors import DeviceBusyError  # noqa: E402
from tactdeform_hw.transports import port_for_name  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
ENV = dict(os.environ, PYTHONPATH=str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", ""))
WAIT_S = 30.0  # generous: the machine may be busy; nothing here is a timing assertion on speed
#: The safety bound on delivered pulses: the last pulse with current at most this long after SIGKILL
#: (measured median about 50 ms on v1.2 and 75 ms on v2: tools/stop_latency.py --transport usb).
OFF_WITHIN_US = 150_000


class ServedBoard:
    """``emulate --usb`` as a subprocess, and a monitoring connection to its board's record."""

    def __init__(self, firmware: str) -> None:
        self.proc = subprocess.Popen(
            [
                sys.executable,
                "-m",
                "tactdeform_hw.cli",
                "emulate",
                "--usb",
                "--firmware",
                firmware,
                "--quiet",
            ],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            env=ENV,
            cwd=str(REPO),
        )
        assert self.proc.stdout is not None
        self.name = self.proc.stdout.readline().strip()
        assert self.name.startswith(SERVED_PREFIX), self.proc.stderr.read() if self.proc.stderr else ""
        self.monitor = EmulatorClientBackend(self.name[len(SERVED_PREFIX) :])
        self.procs: list[subprocess.Popen[str]] = []

    def status(self, since_us: float = 0.0) -> dict[str, Any]:
        return self.monitor.board_status(since_us)

    def device_us(self, t: float) -> float:
        """Board time of ``time.monotonic()`` value ``t`` (both processes share the monotonic clock)."""
        return (t - float(self.status(float("inf"))["t0"])) * 1e6

    def cli(self, *args: str) -> subprocess.Popen[str]:
        proc = subprocess.Popen(
            [sys.executable, "-m", "tactdeform_hw.cli", *args, "--device", self.name],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            env=ENV,
            cwd=str(REPO),
            start_new_session=True,
        )
        self.procs.append(proc)
        return proc

    def wait_stimulating(self, timeout_s: float = WAIT_S) -> None:
        end = time.monotonic() + timeout_s
        while time.monotonic() < end:  # the last 50 ms of the record only: a light poll
            st = self.status(self.device_us(time.monotonic()) - 50e3)
            if st["last_current_pulse_us"] is not None and st["now_us"] - st["last_current_pulse_us"] < 20e3:
                return
            time.sleep(0.02)
        raise AssertionError("the board never delivered current")

    def close(self) -> None:
        for proc in self.procs:
            if proc.poll() is None:
                proc.kill()
            proc.communicate(timeout=WAIT_S)
        self.monitor.close()
        self.proc.send_signal(signal.SIGINT)
        self.proc.communicate(timeout=WAIT_S)


@pytest.fixture(params=["v1.2", "v2"])
def board(request: pytest.FixtureRequest) -> Iterator[ServedBoard]:
    b = ServedBoard(request.param)
    try:
        yield b
    finally:
        b.close()


HOLD = ("send", "--pattern", "all:1", "--current-ua", "500", "--hold-ms", "20000")


def test_killed_owner_leaves_the_board_off_within_150_ms(board: ServedBoard) -> None:
    owner = board.cli(*HOLD)
    board.wait_stimulating()
    time.sleep(0.1)
    t_kill = time.monotonic()
    os.kill(owner.pid, signal.SIGKILL)
    kill_us = board.device_us(t_kill)
    _, err = owner.communicate(timeout=WAIT_S)
    assert "gone: all-off sent (heights 0 proved" in err, err  # the guardian read the firmware's answer
    # the guardian takes the released claim and switches off; give it (generously) time to finish
    end = time.monotonic() + WAIT_S
    while time.monotonic() < end:
        st = board.status(float("inf"))
        if st["now_us"] > kill_us + 0.5e6:
            break
        time.sleep(0.05)
    st = board.status(kill_us - 20e3)
    assert st["last_current_pulse_us"] is not None  # stimulating up to the kill: the stop is real
    last = board.status(kill_us)["last_current_pulse_us"]
    assert last is not None and last - kill_us < OFF_WITHIN_US, (last, kill_us)
    # and nobody holds the board any more: a new program takes it
    again = board.cli("send", "--pattern", "all:0", "--current-ua", "500", "--hold-ms", "0")
    out, err = again.communicate(timeout=WAIT_S)
    assert again.returncode == 0, err


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT])
def test_a_stop_signal_to_a_usb_owner_switches_the_board_off(board: ServedBoard, sig: signal.Signals) -> None:
    owner = board.cli(*HOLD)
    board.wait_stimulating()
    time.sleep(0.1)
    t_sig = time.monotonic()
    os.kill(owner.pid, sig)
    sig_us = board.device_us(t_sig)
    _, err = owner.communicate(timeout=WAIT_S)
    assert f"stopped by {sig.name}; every channel off" in err and "Traceback" not in err
    end = time.monotonic() + WAIT_S
    while board.status(float("inf"))["now_us"] < sig_us + 0.5e6 and time.monotonic() < end:
        time.sleep(0.05)
    last = board.status(sig_us)["last_current_pulse_us"]
    assert last is None or last - sig_us < OFF_WITHIN_US, (last, sig_us)


def test_a_second_program_is_refused_and_writes_nothing(board: ServedBoard) -> None:
    owner = board.cli(*HOLD)
    board.wait_stimulating()
    second = board.cli("send", "--pattern", "all:1", "--current-ua", "500", "--hold-ms", "100")
    _, err = second.communicate(timeout=WAIT_S)
    assert second.returncode != 0
    assert "in use by another program" in err and "nothing was written" in err, err
    assert "Traceback" not in err
    clients = [c for c in board.status()["clients"] if c["pid"] == second.pid]
    assert clients, board.status()["clients"]  # it did reach the bus ...
    assert all(c["bytes_in"] == 0 and not c["claimed"] for c in clients), clients  # ... and sent nothing
    board.wait_stimulating()  # the owner is untouched
    assert owner.poll() is None


# --- the kernel's serial driver: never detached from a program that holds the tty ---------------------


def _fake_tty(root: Path, dev: EmulatedUsbDevice, interface: int, tty: str) -> None:
    d = root / "sys" / "bus" / "usb" / "devices" / f"{dev.bus}-{dev.address}:1.{interface}" / "tty" / tty
    d.mkdir(parents=True)


def test_usb_open_refuses_a_board_whose_tty_another_program_holds(tmp_path: Path) -> None:
    be = EmulatedUsbBackend()
    dev = be.device
    _fake_tty(tmp_path, dev, 0, "ttyACM0")
    asked: list[str] = []

    def holders(path: str) -> list[tuple[int, str]]:
        asked.append(path)
        return [(4242, "picocom /dev/ttyACM0")] if path.endswith("/ttyACM0") else []

    port = UsbCdcPort(
        0x303A, 0x1001, backend=be, sysfs_root=str(tmp_path / "sys"), dev_root="/dev", holders=holders
    )
    with pytest.raises(DeviceBusyError) as ei:
        port.open()
    msg = str(ei.value)
    assert "pid 4242 (picocom /dev/ttyACM0)" in msg and "/dev/ttyACM0" in msg and "cdc_acm" in msg
    assert msg.endswith("nothing was written to it")
    assert ei.value.holders == [(4242, "picocom /dev/ttyACM0")]
    assert asked == ["/dev/ttyACM0"]
    assert dev.kernel_bound == {0, 1}  # the serial driver still has the board
    assert dev.claims == {} and dev.bytes_accepted == 0 and not port.is_open


def test_usb_open_detaches_the_serial_driver_when_nobody_holds_the_tty(tmp_path: Path) -> None:
    be = EmulatedUsbBackend()
    _fake_tty(tmp_path, be.device, 0, "ttyACM0")
    port = UsbCdcPort(0x303A, 0x1001, backend=be, sysfs_root=str(tmp_path / "sys"), holders=lambda path: [])
    port.open()
    try:
        assert be.device.kernel_bound == set() and port.detached == [0, 1]
    finally:
        port.close()
    assert be.device.kernel_bound == {0, 1}  # given back


def test_only_a_board_that_outlives_its_owner_gets_a_usb_guardian() -> None:
    assert port_for_name("usb:303a:1001", timeout=0.1, baudrate=921600).guardable  # the system's libusb
    assert not port_for_name("usb-emulator", timeout=0.1, baudrate=921600).guardable  # dies with us


@pytest.mark.parametrize(
    ("extra", "says"),
    [
        (["--untimed"], "--usb serves the timed firmware model"),
        (["--build", "wifi"], "--build wifi: a board on USB runs the serial build"),
    ],
)
def test_emulate_usb_refuses_what_a_usb_board_is_not(
    extra: list[str], says: str, capsys: pytest.CaptureFixture[str]
) -> None:
    from tactdeform_hw.cli import main

    assert main(["emulate", "--usb", *extra]) != 0
    err = capsys.readouterr().err
    assert says in err and "Traceback" not in err
