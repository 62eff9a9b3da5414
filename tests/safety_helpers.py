"""Test doubles shared by the safety and driver tests."""

from __future__ import annotations

from typing import Any

from tactdeform_hw.emulator import Emulator
from tactdeform_hw.emulator.hazards import Hazard, HazardKind
from tactdeform_hw.emulator.transport import EmulatorPort

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


def assert_fault_free(summary: dict[str, Any], failed: list[int], *, sessions: int, min_pulses: int) -> None:
    """A fault-free campaign's verdict, judged on delivered pulses: nothing above a limit, nothing on an
    electrode meant off, no byte lost, no defect, no failed session — over enough pulses to mean it."""
    assert summary["sessions"] == sessions
    assert summary["over_limit_pulses"] == 0
    assert summary["meant_off_pulses"] == 0
    assert summary["bytes_lost"] == 0
    assert summary["defects_hit"] == []
    assert summary["failed_sessions"] == 0, failed[:10]
    assert summary["pulses"] > min_pulses  # the sessions stimulate: the verdict is about real pulses
