"""A stop that always happens: every stimulating command, every stop signal, a dead owner, an exception.

The emulated board is served on a real pseudo-terminal in the test process (:class:`BoardWatch` judges
each chunk the firmware model parsed: does any channel still receive current?), and the commands run as
separate processes that open it by path, exactly as on a bench.  Every verdict is on what the emulated
board holds after the stop, never on what the host meant to send.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from tactdeform_hw.device import StimConfig, open_device
from tactdeform_hw.device.driver.serial_driver import find_holders
from tactdeform_hw.device.safety import failsafe as fs_mod
from tactdeform_hw.device.safety.guardian import (
    LEAD_ZEROS,
    PACKET_BYTES,
    RESYNC_ZEROS,
    off_packet,
    pace_for,
    stop_packet,
    zeros_gap_s,
)
from tactdeform_hw.emulator import Emulator
from tactdeform_hw.emulator.serving.pty_server import PtyServer
from tactdeform_hw.protocol.state import BoardState

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "tools"))
from stop_latency import BoardWatch, delivering  # noqa: E402

ENV = dict(os.environ, PYTHONPATH=str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", ""))
WAIT_S = 60.0  # generous: the machine may be busy; nothing here is a timing assertion


class Board:
    def __init__(self) -> None:
        self.watch = BoardWatch()
        self.server = PtyServer(self.watch).start()  # type: ignore[arg-type]
        self.path = self.server.path
        self.procs: list[subprocess.Popen[str]] = []

    def run(self, argv: list[str]) -> subprocess.Popen[str]:
        proc = subprocess.Popen(
            argv,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            env=ENV,
            cwd=str(REPO),
            start_new_session=True,
        )
        self.procs.append(proc)
        return proc

    def cli(self, *args: str) -> subprocess.Popen[str]:
        return self.run([sys.executable, "-m", "tactdeform_hw.cli", *args, "--device", self.path])

    def holders(self) -> list[int]:
        me = os.getpid()
        return [pid for pid, _ in find_holders(self.path) if pid != me]

    def wait_free(self, timeout: float = WAIT_S) -> bool:
        """Owner and guardian gone: nobody but this process (the emulator) holds the port."""
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            if not self.holders():
                return True
            time.sleep(0.01)
        return False

    def close(self) -> None:
        for proc in self.procs:
            if proc.poll() is None:
                proc.kill()
            try:
                proc.communicate(timeout=WAIT_S)
            except (subprocess.TimeoutExpired, ValueError):
                pass
        self.wait_free(10.0)  # a guardian finishes its all-off and exits on its own
        self.server.stop()


@pytest.fixture
def board() -> Iterator[Board]:
    b = Board()
    try:
        yield b
    finally:
        b.close()


def board_is_off(state: BoardState) -> bool:
    n = state.electrode_num
    return (
        not delivering(state)
        and state.pulse_height == 0
        and state.sense_pulse_height == 0
        and list(state.stim_pattern[:n]) == [0] * n
    )


# --- every stimulating command × every stop signal ----------------------------------------------------------


def _command(name: str, tmp: Path) -> list[str]:
    if name == "send":
        return ["send", "--pattern", "all:1", "--current-ua", "500", "--hold", "120"]
    if name == "play":
        pattern = tmp / "hold.json"
        step = {
            "delay": {"ON": 120000, "OFF": 0},
            "pattern": [1, 0] * 16,
            "params": {"frequency": 125, "stim_mode": 1},
        }
        pattern.write_text(json.dumps({"Execution": True, "Simulation": True, "Pattern_Data": [[step]]}))
        return ["play", str(pattern), "--current-ua", "500", "--quiet"]
    if name == "render":
        return [
            "render",
            "--scene",
            "cube",
            "--trajectory",
            "explore",
            "--realtime",
            "--current-ua",
            "500",
            "--quiet",
        ]
    if name == "study":
        return [
            "study",
            "task1",
            "--quick",
            "--realtime",
            "--current-ua",
            "500",
            "--out",
            str(tmp / "study"),
            "--no-timed",
            "--no-pictures",
            "--quiet",
        ]
    if name == "calibrate":
        keys = tmp / "keys.txt"
        keys.write_text("+ + + + +\n")
        return [
            "calibrate",
            "--participant",
            "P01",
            "--out",
            str(tmp / "P01.json"),
            "--keys",
            str(keys),
            "--hold-ms",
            "120000",
        ]
    raise AssertionError(name)


COMMANDS = ("send", "play", "render", "study", "calibrate")
SIGNALS = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP, signal.SIGQUIT)


@pytest.mark.parametrize("sig", SIGNALS, ids=lambda s: signal.Signals(s).name)
@pytest.mark.parametrize("command", COMMANDS)
def test_every_stimulating_command_switches_off_on_every_stop_signal(
    board: Board, tmp_path: Path, command: str, sig: int
) -> None:
    proc = board.cli(*_command(command, tmp_path))
    assert board.watch.wait(True, WAIT_S), (command, board.watch.state(), proc.poll())
    assert proc.poll() is None  # still running and stimulating when the signal comes
    os.kill(proc.pid, sig)
    _, err = proc.communicate(timeout=WAIT_S)
    name = signal.Signals(sig).name
    assert proc.returncode == (130 if sig == signal.SIGINT else 128 + sig), err
    assert "Traceback" not in err, err
    assert err.strip().splitlines()[-1] == f"tactdeform-hw {command}: stopped by {name}; every channel off", (
        err
    )
    state = board.watch.state()
    assert board_is_off(state), state
    assert not board.watch.emulator.locked
    assert board.wait_free(), board.holders()  # the guardian saw the clean close and left


# The stop handler runs wherever the signal caught the main thread.  A command's owner writes an audit line
# for every command it sends, so the signal that comes the moment the board goes on (as in the test above) can
# land while that line is being written, with the audit log's lock held; the handler's own all-off then writes
# there too.  This owner's audit stream raises the signal itself from inside that write, every time.
SIGNAL_INSIDE_AUDIT = """
import os, signal, sys
from argparse import Namespace
from tactdeform_hw.cli.common import hold, run_command
from tactdeform_hw.cli.delivered import DeliveryLog
from tactdeform_hw.device import StimConfig, open_device
from tactdeform_hw.device.safety import failsafe

path, sig, how, record = sys.argv[1], int(sys.argv[2]), sys.argv[3], sys.argv[4]

class Stream:
    armed = False
    def __init__(self):
        self.out = open(record, "w")
    def write(self, text):
        self.out.write(text)
        if self.armed:
            self.armed = False
            os.kill(os.getpid(), sig)  # its handler runs here, inside the audit log's write
    def flush(self):
        self.out.flush()

def command(args):
    stream = Stream()
    log = DeliveryLog(stream, command="send")
    dev = open_device(path, audit=log)
    dev.configure(StimConfig(current_ua=600))
    if how == "stuck":  # an all-off that cannot finish: the deadline ends the process
        failsafe.STOP_DEADLINE_S = 0.5
        def stuck(lock=__import__("threading").Lock()):
            lock.acquire()
            lock.acquire()
        dev.close = stuck
    stream.armed = True  # the next line is the audit of the frame that switches the board on
    dev.send_pattern([1] * 32)
    hold(dev, 120)
    return 0

sys.exit(run_command(command, Namespace(command="send")))
"""


@pytest.mark.parametrize("sig", SIGNALS, ids=lambda s: signal.Signals(s).name)
def test_a_stop_signal_inside_the_audit_logs_own_write_switches_off(
    board: Board, tmp_path: Path, sig: int
) -> None:
    record = tmp_path / "audit.jsonl"
    proc = board.run([sys.executable, "-c", SIGNAL_INSIDE_AUDIT, board.path, str(sig), "lock", str(record)])
    _, err = proc.communicate(timeout=WAIT_S)
    name = signal.Signals(sig).name
    assert proc.returncode == 128 + sig, err
    assert "Traceback" not in err, err
    assert err.strip().splitlines()[-1] == f"tactdeform-hw send: stopped by {name}; every channel off", err
    assert board_is_off(board.watch.state()), board.watch.state()
    assert board.wait_free(), board.holders()
    # the frame was written before the stop (its bytes and the all-off's may reach the board in one read)
    lines = [json.loads(line) for line in record.read_text().splitlines()]
    after = lines[[i for i, r in enumerate(lines) if r.get("cmd") == "PATTERN" and 1 in r["value"]][0] + 1 :]
    # the last height written is 0 (the all-off may end with a request whose reply proves it was read)
    assert [r["value"] for r in after if r["type"] == "tx" and r["cmd"] == "PULSE_HEIGHT"][-1:] == [0], after
    assert any(r["type"] == "event" and r["event"] == "signal" and r["signal"] == name for r in after), after


def test_a_stop_that_cannot_finish_ends_the_process_and_the_guardian_switches_off(
    board: Board, tmp_path: Path
) -> None:
    """Whatever blocks the handler's all-off for good, the process does not outlive the stop deadline: it
    exits, and its guardian switches the board off."""
    proc = board.run(
        [
            sys.executable,
            "-c",
            SIGNAL_INSIDE_AUDIT,
            board.path,
            str(int(signal.SIGTERM)),
            "stuck",
            str(tmp_path / "audit.jsonl"),
        ]
    )
    _, err = proc.communicate(timeout=WAIT_S)
    assert proc.returncode == 128 + signal.SIGTERM, err
    assert "the all-off did not finish within 0.5 s" in err, err
    assert "gone: all-off sent (heights 0 proved" in err, err
    assert board.watch.on_since is not None
    assert board_is_off(board.watch.state()), board.watch.state()
    assert board.wait_free(), board.holders()


def test_a_stop_never_glues_its_line_onto_an_unfinished_progress_line(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """The stop handler raises wherever the signal caught the main thread: here, right after the first
    write of a progress line (a ``print`` writes the text and its newline separately)."""
    import io

    from tactdeform_hw.cli import common

    class Stderr(io.StringIO):
        signal_due = True

        def write(self, s: str) -> int:
            n = super().write(s)
            if self.signal_due:
                self.signal_due = False
                raise KeyboardInterrupt  # what the stop handler raises for SIGINT
            return n

    err = Stderr()
    monkeypatch.setattr(sys, "stderr", err)
    with pytest.raises(KeyboardInterrupt):
        common.progress("centre: raise until uncomfortable, then accept  [10 µA]")
    common._report_stop("calibrate", signal.SIGINT, 1, True)
    assert err.getvalue().splitlines() == [
        "centre: raise until uncomfortable, then accept  [10 µA]",
        "tactdeform-hw calibrate: stopped by SIGINT; every channel off",
    ]


# --- an owner that runs no code: the guardian ---------------------------------------------------------------


OWNER = """
import os, signal, sys, time
from tactdeform_hw.device import StimConfig, open_device
signal.signal(signal.SIGHUP, signal.SIG_DFL)  # a hang-up kills it, even under nohup (SIG_IGN inherited)
dev = open_device(sys.argv[1])
dev.configure(StimConfig(current_ua=1000))
dev.send_pattern([1, 2, 0, 0] * 8)
print(dev.guardian.pid, flush=True)
if sys.argv[2] == "exit":
    os._exit(3)  # a crash: no finally, no atexit, no handler
time.sleep(600)
"""


@pytest.mark.parametrize("how", ["SIGKILL", "crash"])
def test_guardian_switches_off_when_the_owner_dies_without_running_code(board: Board, how: str) -> None:
    proc = board.run([sys.executable, "-c", OWNER, board.path, "exit" if how == "crash" else "sleep"])
    guardian_pid = int(proc.stdout.readline())  # type: ignore[union-attr]
    assert board.watch.wait(True, WAIT_S)
    assert os.getsid(guardian_pid) == guardian_pid != os.getsid(proc.pid)  # its own session
    t0 = time.monotonic()
    if how == "SIGKILL":
        os.kill(proc.pid, signal.SIGKILL)
    assert board.watch.wait(False, WAIT_S), _still_on(board, proc, guardian_pid)
    assert board.watch.safe_since is not None
    if how == "SIGKILL":  # a loose bound; tools/stop_latency.py measures the real figure
        assert board.watch.safe_since - t0 < 1.0
    _, err = proc.communicate(timeout=WAIT_S)
    assert board.wait_free()
    assert "gone: all-off sent (heights 0 proved" in err and "all-off pattern proved" in err, err
    assert board_is_off(board.watch.state()), board.watch.state()
    assert not board.watch.emulator.locked


def test_guardian_survives_the_terminal_signals_that_kill_its_owner(board: Board) -> None:
    """Ctrl-C or a hang-up go to the owner's whole process group; the guardian is not in it."""
    proc = board.run([sys.executable, "-c", OWNER, board.path, "sleep"])
    guardian_pid = int(proc.stdout.readline())  # type: ignore[union-attr]
    assert board.watch.wait(True, WAIT_S)
    os.killpg(proc.pid, signal.SIGHUP)  # the owner has no handler: it dies of it, running no code
    assert board.watch.wait(False, WAIT_S), _still_on(board, proc, guardian_pid)
    proc.communicate(timeout=WAIT_S)
    assert board.wait_free()
    assert _gone(guardian_pid)  # done and gone


def _still_on(board: Board, proc: subprocess.Popen[str], guardian_pid: int) -> str:
    """What a failed stop leaves to read: the board's state, the bytes it took in, and what the owner and
    its guardian wrote on stderr (the guardian is killed first: it holds the same pipe)."""
    bytes_in = board.watch.bytes_in
    try:
        os.kill(guardian_pid, signal.SIGKILL)
    except OSError:
        pass
    try:
        _, err = proc.communicate(timeout=10)
    except subprocess.TimeoutExpired:
        err = "(stderr still open after 10 s)"
    return f"{board.watch.state()}; {bytes_in} bytes in; stderr:\n{err}"


def _gone(pid: int) -> bool:
    """Exited (a zombie nobody reaped yet counts: its parent, the owner, is dead)."""
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().rsplit(")", 1)[1].split()[0] in ("Z", "X")
    except OSError:
        return True


def test_guardian_leaves_quietly_after_a_clean_close(board: Board) -> None:
    with open_device(board.path) as dev:
        g = dev.guardian
        assert g is not None and g.alive
        dev.configure(StimConfig(current_ua=700))
        dev.send_pattern([1] * 32)
        assert board.watch.wait(True, WAIT_S)
    assert g.proc.returncode == 0 and board_is_off(board.watch.state())
    n = board.watch.bytes_in
    time.sleep(0.1)
    assert board.watch.bytes_in == n  # it wrote nothing after the owner's own all-off


def test_in_process_emulator_declares_nothing_to_guard() -> None:
    with open_device("emulator") as dev:
        assert dev.guardian is None
        assert not getattr(dev.port, "guardable", False)


# --- the stop packets: safe at every entry point, under every tail loss -------------------------------------


def _stimulating_emulator() -> Emulator:
    emu = Emulator()
    emu.feed(b"\xfc\x20")  # 32 electrodes
    emu.feed(b"\xfe" + bytes([1, 2] * 16))
    emu.feed(b"\xfb\x32\x00")  # 50 codes (500 µA)
    emu.feed(b"\xfa\xc8\x00\xf6\x7d\x00\xf7\x2d")
    return emu


WATCHED = ("pulse_height", "sense_pulse_height", "electrode_num", "pulse_width", "sense_pulse_width")
# What the owner may have left half-received: every command with a payload, cut after each payload byte.
PARTIALS = [b""] + [
    bytes([op]) + payload[:k]
    for op, payload in (
        (0xFB, b"\x34\x00"),
        (0xFA, b"\xc8\x00"),
        (0xF6, b"\x7d\x00"),
        (0xF9, b"\x00"),
        (0xF8, b"\x00"),
        (0xF7, b"\x2d"),
        (0xFD, b"\x01"),
        (0xFC, b"\x20"),
        (0xFE, bytes([1, 2] * 16)),
    )
    for k in range(len(payload))
]


def _peaks(emu: Emulator, data: bytes) -> dict[str, int]:
    peak = {k: emu.state().as_dict()[k] for k in WATCHED}
    for b in data:
        emu.feed(bytes([b]))
        st = emu.state().as_dict()
        for k in WATCHED:
            peak[k] = max(peak[k], st[k])
    return peak


@pytest.mark.parametrize("partial", PARTIALS, ids=lambda b: b.hex() or "boundary")
def test_stop_packet_never_raises_a_value_whatever_it_lands_on_and_whatever_tail_is_lost(
    partial: bytes,
) -> None:
    stop = stop_packet()
    assert stop[:LEAD_ZEROS] == bytes(LEAD_ZEROS) and len(stop) <= 64
    # the bound: what the owner's half command becomes when finished with zeros (the owner's own bytes)
    ref = _stimulating_emulator()
    ref.feed(partial)
    bound = _peaks(ref, bytes(RESYNC_ZEROS))
    for cut in range(len(stop) + 1):
        emu = _stimulating_emulator()
        emu.feed(partial)
        # a packet whose tail was lost at ``cut``, then the guardian's retry: zeros, the packet whole
        peak = _peaks(emu, stop[:cut] + bytes(RESYNC_ZEROS) + stop)
        for k in WATCHED:
            assert peak[k] <= bound[k], (partial.hex(), cut, k, peak[k], bound[k])
        st = emu.state()
        assert st.pulse_height == 0 and st.sense_pulse_height == 0 and not delivering(st)
        assert not emu.locked


@pytest.mark.parametrize("n", [1, 32, 244, 245, 255])
def test_off_packet_after_the_proof_never_raises_and_never_locks(n: int) -> None:
    off = off_packet(n)
    for cut in range(len(off) + 1):
        emu = _stimulating_emulator()
        emu.feed(stop_packet())  # proved: heights 0, parser at a boundary
        peak = _peaks(emu, off[:cut] + stop_packet())
        assert peak["pulse_height"] == 0 and peak["sense_pulse_height"] == 0
        assert not emu.locked
    emu = _stimulating_emulator()
    emu.feed(stop_packet() + off)
    st = emu.state()
    assert st.electrode_num == n and list(st.stim_pattern[:n]) == [0] * n


def _guardian_on_timed_board(
    owner_tail: bytes, offset_us: float, link: str
) -> tuple[float, float, int, list[int]]:
    """The timed firmware over ``link``: an owner drives 16 of 32 channels at 500 µA, dies having written
    ``owner_tail`` (a torn frame, or a burst that overflows the queue), and ``offset_us`` later the guardian's
    bytes follow as it sends them when no proof comes back (the worst case: every retry, each 20 ms after
    the packet before, its zeros spaced by :func:`zeros_gap_s` for this configuration).  Returns the
    largest current delivered from the owner's death on, the largest once the guardian is done, the final
    pulse height, and the host offsets of the guardian's bytes the receive queue discarded."""
    from tactdeform_hw.emulator import HazardKind
    from tactdeform_hw.emulator.timed.model_v1_2 import TimedEmulator

    from .safety_helpers import configure_v12_tactdeform

    emu = TimedEmulator(link=link)
    t = configure_v12_tactdeform(emu)
    emu.advance_to(t)
    death = t + 100
    if owner_tail:
        emu.write(owner_tail, at_us=death)
    g = death + offset_us
    stop = stop_packet()
    emu.write(stop, at_us=g)
    gap_us = zeros_gap_s(pace_for(125, 32, 200, 45, 0)[1]) * 1e6
    t_stop = g
    for _ in range(3):  # no proof came: the zeros a packet at a time, then the packet again
        tk = t_stop + 20_000
        for i in range(RESYNC_ZEROS // PACKET_BYTES):
            emu.write(bytes(PACKET_BYTES), at_us=tk + i * gap_us)
        t_stop = tk + RESYNC_ZEROS // PACKET_BYTES * gap_us
        emu.write(stop, at_us=t_stop)
    t_off = t_stop + 20_000
    emu.write(off_packet(32), at_us=t_off)
    emu.advance_to(t_off + 60_000)
    table = emu.reports.pulse_table(death)
    current = table["current_ua"]
    done = table["start_us"] > t_off
    lost = [
        int(h.detail["host_offset"])
        for h in emu.hazards
        if h.kind is HazardKind.QUEUE_OVERFLOW and h.time_us is not None and h.time_us > g
    ]
    return (
        float(current.max()) if current.size else 0.0,
        float(current[done].max()) if done.any() else 0.0,
        emu.state().pulse_height,
        lost,
    )


@pytest.mark.parametrize("link", ["usb", "uart"])
def test_guardian_bytes_on_the_timed_board_never_deliver_more_than_the_owner_left(link: str) -> None:
    """Judged on the pulses the timed firmware delivered: whatever the owner tore (every cut of a frame,
    alone or after a burst that overflowed the queue) and whenever the guardian's bytes land (at once, into
    a full queue, or after the drain wait), no pulse exceeds the owner's 500 µA, and none carries current
    once the guardian is done."""
    from tactdeform_hw import protocol as p

    frame = p.encode_pattern(bytes([1, 0] * 16), electrode_num=32) + p.encode_pulse_height(50)
    cases = [(frame[:k], off) for k in range(len(frame)) for off in (0.0, 36_400.0)]
    cases += [(frame * 8 + frame[:k], off) for k in range(0, len(frame), 5) for off in (0.0, 36_400.0)]
    for tail, off in cases:
        peak, after, height, lost = _guardian_on_timed_board(tail, off, link)
        assert peak <= 500.0 + 1e-6 and after == 0.0 and height == 0, (tail.hex(), off, peak, after, height)
        if len(tail) < len(frame):  # (a burst that overflowed the queue may take the guardian's bytes too)
            assert lost == [], (tail.hex(), off, lost)


# --- exceptions and a blocked main thread -------------------------------------------------------------------


def test_an_exception_anywhere_in_a_command_switches_off(board: Board) -> None:
    from argparse import Namespace

    from tactdeform_hw.cli.common import run_command

    def command(args: Namespace) -> int:
        dev = open_device(board.path)  # never closed by the command itself
        dev.configure(StimConfig(current_ua=900))
        dev.send_pattern([1] * 32)
        assert board.watch.wait_seen_on(WAIT_S)
        raise RuntimeError("a bug deep in the command")

    with pytest.raises(RuntimeError, match="a bug deep"):
        run_command(command, Namespace(command="test"))
    assert board_is_off(board.watch.state()), board.watch.state()
    assert board.wait_free()


def test_the_watchdog_runs_while_the_main_thread_is_blocked(board: Board) -> None:
    with fs_mod.StopSession() as session:
        dev = open_device(board.path)
        dev.configure(StimConfig(current_ua=900))
        dev.send_pattern([1] * 32)
        (watched,) = session.watched
        assert watched.device is dev and watched._thread is not None
        assert board.watch.wait_seen_on(WAIT_S)
        # the main thread now blocks (here: on a condition variable) and sends no frame
        assert board.watch.wait(False, WAIT_S), board.watch.state()
        assert watched.watchdog_trips >= 1 and not dev.closed
    assert dev.closed and board.wait_free()


def test_the_command_line_runs_every_command_under_the_stop_session(monkeypatch: pytest.MonkeyPatch) -> None:
    from tactdeform_hw import cli
    from tactdeform_hw.cli import common

    seen: list[str] = []
    real = common.run_command

    def spy(func: Any, args: Any) -> int:
        seen.append(args.command)
        return real(func, args)

    monkeypatch.setattr(common, "run_command", spy)
    assert cli.main(["send", "--pattern", "all:0", "--electrodes", "4"]) == 0
    assert seen == ["send"]


def test_a_second_signal_during_the_all_off_is_ignored(board: Board) -> None:
    """An impatient second Ctrl-C must not cut the first one's all-off in half."""
    dev = open_device(board.path)
    fs = fs_mod.FailSafe(dev, thread=False, signals=False).start()
    dev.configure(StimConfig(current_ua=800))
    dev.send_pattern([1] * 32)
    assert board.watch.wait(True, WAIT_S)
    real_close = dev.close

    def close_with_second_signal() -> None:
        fs_mod._on_stop_signal(signal.SIGINT, None)  # arrives while the first stop is closing
        real_close()

    dev.close = close_with_second_signal  # type: ignore[method-assign]
    with pytest.raises(fs_mod.SignalStop) as exc:
        fs_mod._on_stop_signal(signal.SIGTERM, None)
    assert exc.value.code == 128 + signal.SIGTERM and exc.value.all_off
    assert board_is_off(board.watch.state())
    fs.stop()
    assert board.wait_free()


def test_the_stop_latency_tool_measures_both_stops(capsys: pytest.CaptureFixture[str]) -> None:
    import stop_latency

    assert stop_latency.main(["--trials", "1", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    for sig in ("SIGTERM", "SIGKILL"):
        assert out[sig]["trials"] == 1 and 0 < out[sig]["max_ms"] < 1000
