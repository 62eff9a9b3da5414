"""Firmware identification: a board is driven only in the version it has proved by a reply only that
version gives.  From every parser state either firmware ends at a command boundary with every current off
and no pattern entry made from the identification's bytes; silence, a locked parser or an answer neither
version gives is a refusal, never a default."""

from __future__ import annotations

import itertools

import pytest

from tactdeform_hw.device.driver.base import LinkState
from tactdeform_hw.device.driver.config import StimConfig
from tactdeform_hw.device.driver.dialects import DIALECTS
from tactdeform_hw.device.driver.firmware_probe import (
    IDENT_OFF,
    SETTLE_S,
    SIGNATURE,
    FirmwareMismatchError,
    UnidentifiedBoardError,
    check_firmware,
    classify,
    detect_firmware,
)
from tactdeform_hw.device.driver.serial_driver import EtactileKitDevice
from tactdeform_hw.device.driver.v2 import buffer_levels
from tactdeform_hw.emulator import Emulator
from tactdeform_hw.emulator.serving.in_process import EmulatorPort
from tactdeform_hw.protocol import commands as c12
from tactdeform_hw.protocol.commands import V2_COMMANDS as c2
from tactdeform_hw.protocol.firmware import FIRMWARES, V1_2, V2

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


def _detect(emu: Emulator, *, settle: bool = True):
    port = EmulatorPort(emu)
    port.open()
    wait_s = SETTLE_S if settle else 0.0
    return detect_firmware(
        port.write, port.read, port.reset_input_buffer, settle_s=wait_s, sleep=port.pacing_clock.sleep
    )


@pytest.mark.parametrize(("name", "prefix"), V12_STATES, ids=[n for n, _ in V12_STATES])
def test_v12_is_proved_from_every_parser_state(name: str, prefix: bytes) -> None:
    emu = Emulator()
    emu.feed(STIM_V12 + prefix)
    det = _detect(emu)
    assert det.firmware is V1_2 and det.attempts == 1 and det.reply == b"\x04\x04" and det.hv513_count == 4
    s = emu.state()
    assert emu.parser.cmd is None, "left mid-command"
    assert s.electrode_num == 0 and s.pulse_height == 0 and s.sense_pulse_height == 0
    assert s.rx_pending == 0


def test_a_locked_v12_parser_is_refused_not_taken_for_v12() -> None:
    emu = Emulator()
    emu.feed(STIM_V12 + bytes([0xFC, 0x00, 0xFE]))
    assert emu.locked
    with pytest.raises(UnidentifiedBoardError, match="did not answer.*locked v1.2 parser"):
        _detect(emu)
    assert emu.state().rx_pending == 2 * (len(IDENT_OFF) + len(SIGNATURE))


@pytest.mark.parametrize(("name", "prefix"), V2_STATES, ids=[n for n, _ in V2_STATES])
def test_v2_is_proved_from_every_parser_state_and_no_entry_is_made_of_its_bytes(
    name: str, prefix: bytes
) -> None:
    """After the settle wait a cut pattern has timed out: the identification's bytes never complete it,
    so the pattern buffer holds exactly what it held before (no entry from the earlier heights either)."""
    emu = Emulator(firmware="v2")
    emu.feed(STIM_V2 + prefix)
    before = emu.state().stim_pattern
    det = _detect(emu)
    assert det.firmware is V2 and det.attempts == 1 and det.reply == b"\x04\x00\x04"
    s = emu.state()
    assert not s.command_in_progress
    assert s.electrode_num == 0 and s.stim_mode == 0 and s.sense_pulse_height == 0
    assert s.stim_pattern == before


def test_without_the_settle_wait_a_cut_v2_pattern_would_be_completed() -> None:
    """Why the wait is there: the same bytes written at once complete a cut pattern with its heights."""
    emu = Emulator(firmware="v2")
    emu.feed(c2.encode_electrode_num(2) + bytes([0xFE, 0xFF]))
    _detect(emu, settle=False)
    assert emu.state().stim_pattern[0] != 0


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


def test_a_timeout_discarding_part_of_the_identification_still_ends_proved_and_off() -> None:
    """A stale 255-electrode pattern times out while the first chunks are queued (a wait cut short):
    they are discarded with it, the rest is read from a boundary and the signature still proves v2."""
    emu = Emulator(firmware="v2")
    emu.feed(c2.encode_electrode_num(255) + bytes([0xFE]), at_us=0)
    writes = -(-len(IDENT_OFF) // 64) + 1
    times = [1_900_000, 1_950_000, 2_000_001] + [2_000_001 + 1000 * k for k in range(1, 2 * writes)]
    port = _TimedPort(emu, times)
    det = detect_firmware(port.write, port.read, port.reset_input_buffer, settle_s=0.0, sleep=lambda s: None)
    assert det.firmware is V2
    discards = [h for h in emu.hazards if h.kind.value == "command_timeout"]
    assert len(discards) == 1 and discards[0].detail["discarded"] == 192  # the chunks queued by then
    assert emu.state().electrode_num == 0 and not emu.state().command_in_progress
    assert max(emu.state().stim_pattern) == 0


def test_every_suffix_of_the_identification_is_safe_from_a_boundary() -> None:
    """What a partial discard or a lost packet tail leaves: any suffix, read from a boundary, ends at a
    boundary with the count 0 and no height."""
    wire = IDENT_OFF + SIGNATURE
    for k in range(len(wire)):
        for fw in FIRMWARES:
            emu = Emulator(firmware=fw)
            emu.feed(wire[k:])
            s = emu.state()
            assert not emu.parser.processing, (fw, k)
            assert max(s.stim_pattern) == 0, (fw, k)
            if k <= len(IDENT_OFF) - 7:
                assert s.electrode_num == 0 and s.sense_pulse_height == 0, (fw, k)


def test_only_off_bytes_in_the_identification() -> None:
    wire = IDENT_OFF + SIGNATURE
    assert set(wire) <= {0x00, 0xFC, 0xFB, 0xF9, 0xF5, 0xF4}
    assert all(nxt == 0 for b, nxt in itertools.pairwise(wire) if b in (0xFC, 0xFB, 0xF9))
    assert IDENT_OFF.index(0xFB) == 2  # v1.2's height 0 right after the two zeros that end a cut u16
    assert SETTLE_S > (V2.command_timeout_us or 0) / 1e6


def test_the_signature_replies_tell_the_versions_apart() -> None:
    assert classify(b"\x04\x00\x04") is V2 and classify(b"\x00\x00\x00") is V2
    assert classify(b"\x04\x04") is V1_2 and classify(b"\x00\x00") is V1_2
    for bad in (b"", b"\x04", b"\x04\x05", b"\x04\x01\x04", b"\x00" * 4, b"\x04\x00\x05"):
        assert classify(bad) is None, bad
    assert classify(b"\x04\x20\x04", count=0x20) is V2


class _Silent(EmulatorPort):
    """A port whose far end reads nothing and answers nothing (a busy Wi-Fi board, no board at all)."""

    def write(self, data: bytes) -> int:
        self.bytes_written += len(data)
        return len(data)


class _Echo(EmulatorPort):
    """A loopback: every byte comes back."""

    def write(self, data: bytes) -> int:
        self._rx += bytes(data)
        return len(data)


@pytest.mark.parametrize("port_cls", [_Silent, _Echo])
def test_silence_and_an_echo_are_refused_before_any_stimulating_byte(port_cls: type) -> None:
    from tactdeform_hw.device.driver.serial_driver import EtactileKitDevice

    port = port_cls(Emulator())
    with pytest.raises(UnidentifiedBoardError, match="neither eTactileKit firmware"):
        EtactileKitDevice(port)
    assert not port.is_open


def _left_stimulating(firmware: str) -> tuple[EmulatorPort, Emulator]:
    """A board of ``firmware`` left stimulating by a session of its own version that never closed."""
    emu = Emulator(firmware=firmware)
    port = EmulatorPort(emu)
    earlier = EtactileKitDevice(port, firmware=firmware)
    earlier.configure(StimConfig(electrode_count=4, current_ua=500))
    earlier.send_pattern([1] * 4)
    assert emu.state().electrode_num == 4 and set(buffer_levels(emu.state())[:4]) == {1}
    return port, emu


@pytest.mark.parametrize(
    ("board", "driver"), list(itertools.product(FIRMWARES, FIRMWARES)), ids=lambda name: name
)
def test_open_device_drives_the_version_it_was_told_only_on_a_board_that_proves_it(
    board: str, driver: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    """``open_device(firmware=X)`` on a board left stimulating: driven when the board proves X; refused
    naming both versions otherwise, with the board stopped, the port let go and nothing written after the
    identification."""
    from tactdeform_hw.device.driver import serial_driver

    port, emu = _left_stimulating(board)
    mark = emu.received_bytes
    monkeypatch.setattr(serial_driver, "open_port", lambda name, timeout, p=port: p)
    if board == driver:
        dev = serial_driver.open_device("emulator", firmware=driver)
        assert dev.firmware == board and dev.dialect is DIALECTS[FIRMWARES[board]]
        dev.close()
        return
    with pytest.raises(FirmwareMismatchError, match=f"runs firmware {board}.*firmware='{driver}'"):
        serial_driver.open_device("emulator", firmware=driver)
    assert emu.received_bytes - mark == len(IDENT_OFF) + len(SIGNATURE)  # nothing after the identification
    assert not port.is_open
    assert emu.state().electrode_num == 0  # nothing is scanned any more


@pytest.mark.parametrize("firmware", list(FIRMWARES))
def test_auto_detects_the_version_from_every_parser_state_before_any_stimulating_byte(
    firmware: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    """``firmware="auto"`` from every parser state an earlier program can leave: the identification (only
    bytes that carry no current) comes first, the driver then speaks the version the board runs, and a
    frame reaches the board as sent."""
    from tactdeform_hw.device.driver import serial_driver

    spec = FIRMWARES[firmware]
    for name, prefix in _prefixes(spec, (1, 32, 255)):
        emu = Emulator(firmware=firmware)
        port = EmulatorPort(emu)
        emu.feed(prefix)
        mark = len(emu.parser.rx)
        monkeypatch.setattr(serial_driver, "open_port", lambda name, timeout, p=port: p)
        dev = serial_driver.open_device("emulator", firmware="auto")
        assert dev.dialect is DIALECTS[spec], name
        first = bytes(emu.parser.rx)[mark : mark + 520]
        assert set(first) <= set(IDENT_OFF + SIGNATURE) | {0x00}, name
        assert dev.link_state is LinkState.IN_STEP, name
        dev.configure(StimConfig(electrode_count=4, current_ua=200))
        dev.send_pattern([1, 1, 0, 0])
        assert buffer_levels(emu.state())[:4] == [1, 1, 0, 0], name
        dev.close()


def test_a_v12_expectation_on_a_v2_answer_and_the_reverse_are_refused() -> None:
    emu = Emulator(firmware="v2")
    det = _detect(emu)
    with pytest.raises(FirmwareMismatchError, match="runs firmware v2.*firmware='v1.2'"):
        check_firmware("v1.2", det)
    det12 = _detect(Emulator())
    with pytest.raises(FirmwareMismatchError, match="runs firmware v1.2.*firmware='v2'"):
        check_firmware("v2", det12)


@pytest.mark.parametrize("bad", ["v3", None, ""])
def test_open_device_and_the_constructor_refuse_an_unproved_choice(bad: object) -> None:
    """``firmware=None`` once drove v1.2 without asking; no value skips the identification now."""
    from tactdeform_hw.device.driver.serial_driver import EtactileKitDevice, open_device
    from tactdeform_hw.errors import ConfigurationError

    with pytest.raises(
        ConfigurationError, match=f"firmware={bad!r}.*never driven in a version it has not proved"
    ):
        open_device("emulator", firmware=bad)  # type: ignore[arg-type]
    emu = Emulator(firmware="v2")
    with pytest.raises(ConfigurationError, match="firmware="):
        EtactileKitDevice(EmulatorPort(emu), firmware=bad)  # type: ignore[arg-type]
    assert emu.received_bytes == 0


def test_the_constructor_identifies_a_v2_board_and_drives_it_in_v2() -> None:
    """``EtactileKitDevice(port)`` built directly once drove v1.2 without asking; a v1.2 pattern on a v2
    board is read as heights 0x0101 and clamped 4095."""
    from tactdeform_hw.device.driver.config import StimConfig
    from tactdeform_hw.device.driver.serial_driver import EtactileKitDevice

    emu = Emulator(firmware="v2")
    dev = EtactileKitDevice(EmulatorPort(emu))
    assert dev.firmware == "v2"
    dev.configure(StimConfig(electrode_count=8, current_ua=500, pulse_width_us=200))
    dev.send_pattern([1] * 8)
    assert list(emu.state().stim_pattern[:8]) == [50] * 8
    dev.close()
    assert emu.state().electrode_num == 0


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
    assert OpcodeV2.STIM_MODE == Opcode.PULSE_HEIGHT and OpcodeV2.HV513_COUNT == Opcode.HV513_COUNT
    assert V1_2.by_opcode[Opcode.PULSE_HEIGHT].kind == "u16" and V2.by_opcode[OpcodeV2.STIM_MODE].kind == "u8"
    assert 0xF4 not in V1_2.by_opcode


@pytest.mark.parametrize("fw", list(FIRMWARES))
def test_open_device_identifies_by_default_and_counts_the_identification_as_its_own(
    fw: str, tmp_path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """No ``firmware`` argument: the board proves its version before anything stimulating is written, the
    driver speaks it, and the identification's bytes are in the device's byte count and its audit log."""
    import json

    from tactdeform_hw.device.driver.audit import AuditLog
    from tactdeform_hw.device.driver.serial_driver import open_device
    from tactdeform_hw.emulator.serving.urlhandler import protocol_etactile

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
        assert wire.startswith(IDENT_OFF + SIGNATURE) and dev.pacer.stats.bytes_written == len(wire)
        assert dev.identification.settle_s == 0.0  # a board just made: nothing to wait out
    finally:
        dev.close()
    events = [json.loads(line) for line in log.read_text().splitlines()]
    probe = [e for e in events if e.get("event") == "firmware_probe"]
    assert probe and probe[0]["firmware"] == fw
    assert probe[0]["bytes"] == probe[0]["attempts"] * (len(IDENT_OFF) + len(SIGNATURE))
    ident = [e for e in events if e.get("op") == "identify"]
    assert bytes.fromhex("".join(e["hex"] for e in ident)) == IDENT_OFF + SIGNATURE
    first_command = next(i for i, e in enumerate(events) if "hex" in e and e.get("op") != "identify")
    assert events.index(probe[0]) < first_command


def test_every_command_identifies_by_default(capsys: pytest.CaptureFixture[str]) -> None:
    """``send`` without ``--firmware`` on a v2 board drives v2 (per-electrode heights, mode 0)."""
    import json

    from tactdeform_hw.cli import main

    argv = ["send", "--device", "etactile://?firmware=v2&timed=0", "--pattern", "1,0,1", "--electrodes", "3"]
    assert main([*argv, "--current-ua", "200", "--hold-ms", "0", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["emulator_pattern"] == [20, 0, 20] and out["emulator_state"]["stim_mode"] == 0
