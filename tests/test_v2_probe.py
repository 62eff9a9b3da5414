"""Firmware detection: the probe brings either firmware, from every parser state, to a command boundary
with every current off, and tells them apart; ``open_device(firmware="v1.2")`` refuses a v2 board."""

from __future__ import annotations

import itertools

import pytest

from tactdeform_hw.device.firmware_probe import PROBE, FirmwareMismatchError, check_firmware, detect_firmware
from tactdeform_hw.emulator import Emulator
from tactdeform_hw.emulator.transport import EmulatorPort
from tactdeform_hw.protocol import commands as c12
from tactdeform_hw.protocol import commands_v2 as c2
from tactdeform_hw.protocol.firmware import V1_2, V2

STIM_V12 = (
    c12.encode_electrode_num(32)
    + c12.encode_pulse_height(1000)
    + c12.encode_pulse_width(200)
    + c12.encode_sense_height(200)
    + c12.encode_pattern(bytes([1] * 32))
)
STIM_V2 = (
    c2.encode_electrode_num(32)
    + c2.encode_stim_mode(2)
    + c2.encode_sense_height(255)
    + c2.encode_sense_width(50)
    + c2.encode_pulse_width(200)
    + c2.encode_pattern([4095] * 32)
    + c2.encode_stim_mode(0)
)


def _prefixes(spec, electrode_counts: tuple[int, ...]) -> list[tuple[str, bytes]]:
    """Every parser state worth a name: at a boundary, and after each command byte with 0 .. size-1
    payload bytes (payload bytes 0xFF, the worst a stale byte can be)."""
    out = [("boundary", b"")]
    for op, cmd in sorted(spec.by_opcode.items()):
        if cmd.kind is None:
            continue
        for n in electrode_counts if cmd.kind == "pattern" else (0,):
            size = spec.size_of(op, n)
            setup = bytes([0xFC, n]) if cmd.kind == "pattern" else b""
            for k in sorted({0, 1, max(0, size - 1)} if size > 2 else range(size)):
                out.append((f"{cmd.name}(n={n})+{k}", setup + bytes([op]) + b"\xff" * k))
    return out


V12_STATES = _prefixes(V1_2, (1, 32, 255))
V2_STATES = _prefixes(V2, (0, 1, 32, 255))


def _detect(emu: Emulator):
    port = EmulatorPort(emu)
    port.open()
    return detect_firmware(port.write, port.read, port.reset_input_buffer, sleep=lambda s: None)


@pytest.mark.parametrize(("name", "prefix"), V12_STATES, ids=[n for n, _ in V12_STATES])
def test_v12_from_every_parser_state(name: str, prefix: bytes) -> None:
    emu = Emulator()
    emu.feed(STIM_V12 + prefix)
    det = _detect(emu)
    assert det.firmware is V1_2 and det.attempts == 2
    s = emu.state()
    assert emu.parser.cmd is None, "left mid-command"
    assert s["electrode_num"] == 0 and s["pulse_height"] == 0 and s["sense_pulse_height"] == 0
    assert s["rx_pending"] == 0


def test_v12_locked_parser_reads_as_v12_and_reads_nothing() -> None:
    emu = Emulator()
    emu.feed(STIM_V12 + bytes([0xFC, 0x00, 0xFE]))
    assert emu.locked
    assert _detect(emu).firmware is V1_2
    assert emu.state()["rx_pending"] == 2 * len(PROBE)


@pytest.mark.parametrize(("name", "prefix"), V2_STATES, ids=[n for n, _ in V2_STATES])
def test_v2_from_every_parser_state(name: str, prefix: bytes) -> None:
    emu = Emulator(firmware="v2")
    emu.feed(STIM_V2 + prefix)
    det = _detect(emu)
    assert det.firmware is V2 and det.attempts == 1 and det.reply == b"\x00"
    s = emu.state()
    assert not s["command_in_progress"]
    assert s["electrode_num"] == 0 and s["stim_mode"] == 0 and s["sense_pulse_height"] == 0


class _TimedPort:
    """Each write reaches the v2 emulator at the next of the given timer moments (µs)."""

    def __init__(self, emu: Emulator, times_us: list[int]) -> None:
        self.emu = emu
        self.times = times_us
        self.rx = bytearray()

    def write(self, data: bytes) -> int:
        self.rx += self.emu.feed(bytes(data), at_us=self.times.pop(0))
        return len(data)

    def read(self, n: int) -> bytes:
        out = bytes(self.rx[:n])
        del self.rx[:n]
        return out

    def reset_input_buffer(self) -> None:
        self.rx.clear()


def test_v2_probe_partly_discarded_by_a_timeout_still_detects_and_cleans() -> None:
    """A stale 255-electrode pattern times out while the probe's first chunks are queued: they are
    discarded with it, the rest of the probe is read from a boundary."""
    emu = Emulator(firmware="v2")
    emu.feed(c2.encode_electrode_num(255) + bytes([0xFE]), at_us=0)
    writes = -(-(len(PROBE) - 1) // 64) + 1
    times = [1_900_000, 1_950_000, 2_000_001] + [2_000_001 + 1000 * k for k in range(1, writes)]
    port = _TimedPort(emu, times)
    det = detect_firmware(port.write, port.read, port.reset_input_buffer, sleep=lambda s: None)
    assert det.firmware is V2 and det.reply == b"\x00"
    discards = [h for h in emu.hazards if h.kind.value == "command_timeout"]
    assert len(discards) == 1 and discards[0].detail["discarded"] == 192
    assert emu.state()["electrode_num"] == 0 and not emu.state()["command_in_progress"]


def test_every_suffix_of_the_probe_is_safe_from_a_boundary() -> None:
    """What a partial discard leaves: any suffix, read from a boundary, ends at a boundary."""
    for k in range(len(PROBE)):
        for fw in ("v1.2", "v2"):
            emu = Emulator(firmware=fw)
            emu.feed(PROBE[k:])
            busy = emu.state()["command_in_progress"] if fw == "v2" else emu.parser.cmd is not None
            assert not busy, (fw, k)


def test_only_zero_or_less_current_bytes_in_the_probe() -> None:
    assert set(PROBE) <= {0x00, 0xFC, 0xFB, 0xF9, 0xF4}
    assert all(b == 0 for b, nxt in itertools.pairwise(PROBE) if b in (0xFC, 0xFB, 0xF9) for b in [nxt])


def test_open_device_v12_refuses_a_v2_board_and_accepts_v12(monkeypatch: pytest.MonkeyPatch) -> None:
    from tactdeform_hw.device import serial_driver

    for fw, ok in (("v1.2", True), ("v2", False)):
        emu = Emulator(firmware=fw)
        port = EmulatorPort(emu)
        monkeypatch.setattr(serial_driver, "open_port", lambda name, timeout, p=port: p)
        if ok:
            dev = serial_driver.open_device("emulator", firmware="v1.2")
            dev.close()
        else:
            before = len(emu.parser.rx)
            with pytest.raises(FirmwareMismatchError, match="runs firmware v2"):
                serial_driver.open_device("emulator", firmware="v1.2")
            assert len(emu.parser.rx) - before == len(PROBE)  # nothing after the probe
            assert not port.is_open
            assert emu.state()["electrode_num"] == 0


def test_a_v12_expectation_on_a_v2_answer_and_the_reverse_are_refused() -> None:
    emu = Emulator(firmware="v2")
    det = _detect(emu)
    with pytest.raises(FirmwareMismatchError, match="runs firmware v2.*firmware='v1.2'"):
        check_firmware("v1.2", det)
    det12 = _detect(Emulator())
    with pytest.raises(FirmwareMismatchError, match="runs firmware v1.2.*firmware='v2'"):
        check_firmware("v2", det12)


def test_open_device_refuses_an_unknown_firmware_name() -> None:
    from tactdeform_hw.device.serial_driver import open_device
    from tactdeform_hw.errors import ConfigurationError

    with pytest.raises(ConfigurationError, match="firmware='v3'"):
        open_device("emulator", firmware="v3")


def test_cli_firmware_v12_refuses_a_v2_emulator(capsys: pytest.CaptureFixture[str]) -> None:
    from tactdeform_hw.cli import main

    argv = [
        "send",
        "--device",
        "etactile://?firmware=v2",
        "--firmware",
        "v1.2",
        "--pattern",
        "1",
        "--electrodes",
        "1",
        "--current-ua",
        "100",
        "--hold",
        "0",
    ]
    assert main(argv) != 0
    assert "runs firmware v2" in capsys.readouterr().err
    argv[2] = "etactile://?firmware=v1.2"
    assert main(argv) == 0


def test_the_safe_tail_means_the_same_on_both_versions() -> None:
    from tactdeform_hw.protocol.firmware import Opcode, OpcodeV2

    assert OpcodeV2.ELECTRODE_NUM == Opcode.ELECTRODE_NUM and OpcodeV2.SENSE_HEIGHT == Opcode.SENSE_HEIGHT
    assert OpcodeV2.STIM_MODE == Opcode.PULSE_HEIGHT
    assert V1_2.by_opcode[Opcode.PULSE_HEIGHT].kind == "u16" and V2.by_opcode[OpcodeV2.STIM_MODE].kind == "u8"


@pytest.mark.parametrize("fw", ["v1.2", "v2"])
def test_open_device_detects_by_default_and_counts_the_probe_as_its_own(
    fw: str, tmp_path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """No ``firmware`` argument: the board is asked before anything stimulating is written, the driver
    speaks what it answered, and the probe's bytes are in the device's byte count and its audit log."""
    import json

    from tactdeform_hw.device.audit import AuditLog
    from tactdeform_hw.device.serial_driver import open_device
    from tactdeform_hw.emulator.urlhandler import protocol_etactile

    wire = bytearray()
    write = protocol_etactile.Serial.write

    def counted(self, data):  # type: ignore[no-untyped-def]
        wire.extend(data)
        return write(self, data)

    monkeypatch.setattr(protocol_etactile.Serial, "write", counted)
    log = tmp_path / "audit.jsonl"
    dev = open_device(f"etactile://?firmware={fw}&timed=0", audit=AuditLog(log))
    try:
        assert dev.firmware == fw
        assert wire.startswith(PROBE[:-1]) and dev.pacer.stats.bytes_written == len(wire)
    finally:
        dev.close()
    events = [json.loads(line) for line in log.read_text().splitlines()]
    probe = [e for e in events if e.get("event") == "firmware_probe"]
    assert probe and probe[0]["firmware"] == fw and probe[0]["bytes"] == probe[0]["attempts"] * len(PROBE)
    first_command = next(i for i, e in enumerate(events) if "hex" in e)
    assert events.index(probe[0]) < first_command


def test_every_command_detects_by_default(capsys: pytest.CaptureFixture[str]) -> None:
    """``send`` without ``--firmware`` on a v2 board drives v2 (per-electrode heights, mode 0)."""
    import json

    from tactdeform_hw.cli import main

    argv = ["send", "--device", "etactile://?firmware=v2&timed=0", "--pattern", "1,0,1", "--electrodes", "3"]
    assert main([*argv, "--current-ua", "200", "--hold-ms", "0", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["emulator_pattern"] == [20, 0, 20] and out["emulator_state"]["stim_mode"] == 0
