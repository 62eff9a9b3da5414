"""Test doubles shared by the safety and driver tests."""

from __future__ import annotations

from tactdeform_hw.emulator import Emulator
from tactdeform_hw.emulator.transport import EmulatorPort


class RecordingPort(EmulatorPort):
    """An in-process port that keeps every write, so a test can check what reached the wire as well as
    what the emulator made of it."""

    def __init__(self, emulator: Emulator | None = None, **kw: object) -> None:
        super().__init__(emulator, **kw)  # type: ignore[arg-type]
        self.writes: list[bytes] = []

    def write(self, data: bytes) -> int:
        self.writes.append(bytes(data))
        return super().write(data)
