"""One owner and a stop on a serial path, on both firmware versions: the timed board of each version served
on a pseudo-terminal (as ``emulate --pty`` serves it), judged on the pulses it delivered."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from collections.abc import Iterator

import pytest

from tactdeform_hw.device.driver.firmware_probe import IDENT_OFF
from tactdeform_hw.emulator.serving.pty_server import PtyServer

from .conftest import REPO
from .safety_helpers import current_pulses_us

ENV = dict(os.environ, PYTHONPATH=str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", ""))
WAIT_S = 60.0  # generous: only the 150 ms stop bound is a timing assertion, on the board's own clock
STOP_BOUND_US = 150_000.0


@pytest.fixture(params=["v1.2", "v2"])
def served(request: pytest.FixtureRequest) -> Iterator[PtyServer]:
    server = PtyServer(firmware=str(request.param)).start()
    try:
        yield server
    finally:
        server.stop()


def _send(path: str, *extra: str) -> subprocess.Popen[str]:
    return subprocess.Popen(
        [sys.executable, "-m", "tactdeform_hw.cli", "send", "--device", path, *extra],
        stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, env=ENV, start_new_session=True,
    )  # fmt: skip


def _stimulating_owner(served: PtyServer) -> subprocess.Popen[str]:
    proc = _send(served.path, "--pattern", "all:1", "--electrodes", "16", "--current-ua", "500",
                 "--hold-ms", "20000")  # fmt: skip
    end = time.monotonic() + WAIT_S
    while not current_pulses_us(served.board, 0.0):
        assert proc.poll() is None, proc.communicate()[1]
        assert time.monotonic() < end, "the owner never stimulated"
        time.sleep(0.01)
    time.sleep(0.05)
    return proc


@pytest.mark.parametrize("sig", [signal.SIGKILL, signal.SIGTERM])
def test_the_owner_stopped_or_killed_leaves_the_board_off_within_150_ms(served: PtyServer, sig: int) -> None:
    proc = _stimulating_owner(served)
    try:
        sig_us = served.board.device_us(time.monotonic())
        os.kill(proc.pid, sig)
        _, err = proc.communicate(timeout=WAIT_S)
        assert "Traceback" not in err
        assert ("guardian" in err) if sig == signal.SIGKILL else ("every channel off" in err)
        time.sleep(0.3)  # scans go on: a board still on would deliver here
        late = [t for t in current_pulses_us(served.board, sig_us) if t > sig_us + STOP_BOUND_US]
        assert not late, f"{len(late)} pulses with current more than 150 ms after the signal"
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()


def test_a_second_program_is_refused_before_it_writes_a_byte(served: PtyServer) -> None:
    owner = _stimulating_owner(served)
    try:
        before = served.board.received_bytes
        second = _send(
            served.path, "--pattern", "1", "--electrodes", "1", "--current-ua", "100", "--hold-ms", "0"
        )
        _, err = second.communicate(timeout=WAIT_S)
        assert second.returncode == 1 and "in use by another program" in err and "nothing was written" in err
        # what reached the board meanwhile is the owner's own keepalive traffic: fewer bytes than the
        # identification alone, which is the first thing a program that opened the port would write
        assert served.board.received_bytes - before < len(IDENT_OFF)
    finally:
        owner.send_signal(signal.SIGTERM)
        owner.communicate(timeout=WAIT_S)
