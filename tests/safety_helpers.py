"""Test doubles shared by the safety and driver tests."""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any

from tactdeform_hw.emulator import Emulator
from tactdeform_hw.emulator.firmware.hazards import Hazard, HazardKind
from tactdeform_hw.emulator.serving.in_process import EmulatorPort

#: What the closed-loop proof of a command boundary leaves in the emulator's records: the zeros in front
#: of 0xF5 and the padding after the recovery's commands (unknown bytes), and 0xF5's re-detection.
PROBE_RECORDS = frozenset({HazardKind.UNKNOWN_BYTES, HazardKind.HV513_REINIT})


def defects(hazards: list[Hazard]) -> list[Hazard]:
    """The hazards that are firmware defects, not the records of a probe nor a value byte >= 0xF5 the
    host meant as a value (electrode count 255)."""
    return [
        h
        for h in hazards
        if h.kind not in PROBE_RECORDS
        and not (
            h.kind is HazardKind.PAYLOAD_HOLDS_COMMAND_BYTE and h.detail.get("meant_as_command") is False
        )
    ]


class RecordingPort(EmulatorPort):
    """An in-process port that keeps every write, so a test can check what reached the wire as well as
    what the emulator made of it."""

    def __init__(self, emulator: Emulator | None = None, **kw: object) -> None:
        super().__init__(emulator, **kw)  # type: ignore[arg-type]
        self.writes: list[bytes] = []

    def write(self, data: bytes) -> int:
        self.writes.append(bytes(data))
        return super().write(data)


#: The public calls (and the reopen and wait steps) every firmware's safety campaign must exercise; the v2
#: campaign adds ``measure``.
CAMPAIGN_CALLS = (
    "configure",
    "send_pattern",
    "set_current",
    "keepalive",
    "all_off",
    "suspend",
    "probe",
    "resync",
    "reconnect",
    "hardware_reset",
    "close",
    "reopen",
    "wait",
)


#: Defects the campaigns count and report that the driver does not prevent yet: on v1.2, a scan that starts
#: while a pattern crosses the link uses part new, part old levels; no reply tells the host when the scans
#: run, and a scan at height 0 still reads the pattern, so neither pacing nor a height-0 cover closes it.
#: (v2 copies each new pattern under a mode-2 cover and has no open defect: docs/firmware-v2.md, "Torn
#: scans".)
OPEN_DEFECTS = frozenset({"torn_pattern"})


def assert_fault_free(summary: dict[str, Any], failed: list[int], *, sessions: int, min_pulses: int) -> None:
    """A fault-free campaign's verdict, judged on delivered pulses: nothing above a limit, nothing on an
    electrode meant off, no byte lost, no defect of any kind, no failed session — over enough pulses to
    mean it."""
    assert summary["sessions"] == sessions
    assert summary["over_limit_pulses"] == 0
    assert summary["meant_off_pulses"] == 0
    assert summary["bytes_lost"] == 0
    assert summary["defects_by_kind"] == {}
    assert summary["defects_hit"] == []
    assert summary["failed_sessions"] == 0, (failed[:10], summary["failures"][:5])
    assert summary["pulses"] > min_pulses  # the sessions stimulate: the verdict is about real pulses


def assert_fault_free_but_for(
    summary: dict[str, Any], results: list[Any], kinds: frozenset[str], *, sessions: int, min_pulses: int
) -> None:
    """:func:`assert_fault_free` with the defects of ``kinds`` set apart — counted and reported by the
    campaign, not yet prevented by the driver: every session fails for nothing else."""
    assert summary["sessions"] == sessions
    assert summary["over_limit_pulses"] == 0
    assert summary["meant_off_pulses"] == 0
    assert summary["bytes_lost"] == 0
    assert set(summary["defects_by_kind"]) <= kinds, summary["defects_by_kind"]
    other = [
        r.reproduce()
        for r in results
        if r.over_limit or r.meant_off or r.lost_bytes or set(r.defects) - kinds
    ]
    assert other == [], other[:5]
    assert summary["pulses"] > min_pulses


def wait_until(cond: Callable[[], object], timeout_s: float = 5.0, step_s: float = 0.005) -> bool:
    """Poll ``cond`` until it is true or ``timeout_s`` has passed (wall clock); whether it came true."""
    deadline = time.monotonic() + timeout_s
    while not cond():
        if time.monotonic() > deadline:
            return False
        time.sleep(step_s)
    return True


def delivered_pulses(board: Any, since_us: float = 0.0) -> list[tuple[float, int, float]]:
    """``(start µs, channel, current µA)`` of every pulse a real-time board delivered from ``since_us`` on
    (either firmware's timed model), the model first brought up to the wall clock."""
    with board.lock:
        board.state()
        table = board.timed.reports.pulse_table(since_us)
    return [
        (float(t), int(ch), float(ua))
        for t, ch, ua in zip(table["start_us"], table["channel"], table["current_ua"], strict=True)
    ]


def current_pulses_us(board: Any, since_us: float = 0.0) -> list[float]:
    """Start times (µs) of the pulses that carried current, from ``since_us`` on (see
    :func:`delivered_pulses`)."""
    return [t for t, _, ua in delivered_pulses(board, since_us) if ua > 0]


def configure_v12_tactdeform(emu: Any) -> float:
    """The TactDeform setting on a timed v1.2 board, one command every 12 ms, ending with 16 of 32
    electrodes on at height 50; returns the time (µs) after the last command."""
    from tactdeform_hw import protocol as p

    t = 0.0
    for cmd in (
        p.encode_electrode_num(32),
        p.encode_pattern(bytes(32)),
        p.encode_pulse_width(200),
        p.encode_discharge(45),
        p.encode_frequency(125),
        p.encode_pulse_height(50),
        p.encode_pattern(bytes([1, 0] * 16), electrode_num=32),
    ):
        emu.write(cmd, at_us=t)
        t += 12_000
    return t
