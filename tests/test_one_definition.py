"""The firmware is defined once, in protocol/: every other layer reads its tables, its reader and its
arithmetic, and none keeps a copy of them."""

from __future__ import annotations

import io
import re
import tokenize
from dataclasses import replace
from pathlib import Path

import pytest

from tactdeform_hw.device.driver import audit, pacing
from tactdeform_hw.emulator.firmware import parser as emu_parser
from tactdeform_hw.emulator.timed import model_v1_2 as timed
from tactdeform_hw.emulator.timed.timing import DEFAULT_MODEL, TimingModel
from tactdeform_hw.protocol import firmware_math as fm
from tactdeform_hw.protocol.decoder import decode
from tactdeform_hw.protocol.firmware import V1_2, V2, CommandSpec, Opcode, busy_wait_ticks

PACKAGE = Path(__file__).resolve().parents[1] / "tactdeform_hw"

#: Decimal literals that are the firmware's own (DAC clamp, u8 range, busy-wait and exchange constants)
#: and hex literals of the command bytes 0xF4-0xFE.  0xFF stays allowed: it is also the byte mask.
_FIRMWARE_NUMBERS = {4095, 255, 1020, 6.6, 5.4, 3.3}
_OPCODE_HEX = re.compile(r"0[xX][fF][4-9a-eA-E]$")
#: Literals of the same value that mean something else (file, literal, why).
_ALLOWED = {
    ("emulator/firmware/skin.py", "4095"),  # the board ADC's 12-bit full scale, not the firmware's DAC clamp
    ("viz/array_picture.py", "255"),  # a GIF palette size
}


def _firmware_literals(path: Path) -> list[str]:
    """Code tokens (not strings or comments) that repeat a number the firmware tables hold."""
    out: list[str] = []
    toks = list(tokenize.generate_tokens(io.StringIO(path.read_text(encoding="utf-8")).readline))
    for i, tok in enumerate(toks):
        if tok.type == tokenize.NUMBER:
            text = tok.string.replace("_", "")
            if text.lower().startswith("0x"):
                hit = bool(_OPCODE_HEX.match(text))  # a command byte; other hex (masks, USB ids) are not
            else:
                try:
                    hit = float(text) in _FIRMWARE_NUMBERS
                except ValueError:  # complex, octal or binary literals
                    hit = False
            if hit:
                out.append(f"{tok.start[0]}: {tok.string}")
        elif (
            tok.type == tokenize.OP
            and tok.string == "<<"
            and i + 1 < len(toks)
            and toks[i + 1].string in ("8", "2")
        ):
            what = "u16 decoding" if toks[i + 1].string == "8" else "the sense height's shift"
            out.append(f"{tok.start[0]}: << {toks[i + 1].string} ({what})")
    return out


def test_no_copy_of_the_firmware_numbers_outside_protocol() -> None:
    found = {}
    for path in sorted(PACKAGE.rglob("*.py")):
        rel = path.relative_to(PACKAGE).as_posix()
        if rel.startswith("protocol/"):
            continue
        hits = [h for h in _firmware_literals(path) if (rel, h.split(": ", 1)[1]) not in _ALLOWED]
        if hits:
            found[rel] = hits
    assert found == {}, (
        "firmware numbers repeated outside protocol/ (read them from protocol.firmware): " + repr(found)
    )


def test_the_scanner_finds_what_it_looks_for(tmp_path: Path) -> None:
    """The literal scan above must be able to fail."""
    bad = tmp_path / "bad.py"
    bad.write_text(
        'x = min(v, 4095)\ny = lo | hi << 8\nz = 0xFB\nw = int(us * 2.0 - 5.4)\ns = "4095 in a string"  '
        "# 255\nh = v << 2\n"
    )
    assert [h.split(": ")[1] for h in _firmware_literals(bad)] == [
        "4095",
        "<< 8 (u16 decoding)",
        "0xFB",
        "5.4",
        "<< 2 (the sense height's shift)",
    ]


def test_no_payload_size_table_outside_protocol() -> None:
    size_table = re.compile(r"""["']u16["']\s*:\s*2""")
    copies = [
        p.relative_to(PACKAGE).as_posix()
        for p in PACKAGE.rglob("*.py")
        if "protocol" not in p.parts and size_table.search(p.read_text(encoding="utf-8"))
    ]
    assert copies == []


def test_the_former_copies_are_the_protocol_definitions() -> None:
    assert pacing.estimate_scan_us is fm.estimate_scan_us
    assert pacing.firmware_period_us is fm.firmware_period_us
    assert pacing.SPI_EXCHANGE_US == V1_2.timing.spi_exchange_us
    assert emu_parser._SIZE == V1_2.size_table()
    assert not hasattr(timed, "_SIZE")  # the timed model asks the parser (Parser.plan), holding no copy
    assert TimingModel.for_firmware(V1_2) == DEFAULT_MODEL
    for us in range(0, 300):
        assert (
            DEFAULT_MODEL.delay_ticks(us) == V1_2.timing.delay_ticks(us) == busy_wait_ticks(us, 3, 2.0, 5.4)
        )


def test_the_scan_budget_follows_the_firmware_table() -> None:
    """v2 has no DAAD(0) in the discharge: one exchange shorter per channel, from the table alone."""
    levels = [1] * 32
    v12 = fm.estimate_scan_us(levels, 200, 45, firmware=V1_2)
    v2 = fm.estimate_scan_us(levels, 200, 45, firmware=V2)
    assert v12 - v2 == pytest.approx(32 * V1_2.timing.spi_exchange_us * 1.005)


def test_every_reader_follows_a_changed_table() -> None:
    """A table with another clamp or another command set changes the decoder, the audit log and the
    pacer's helpers, with no edit to them."""
    low_clamp = replace(
        V1_2,
        name="v1.2-lowclamp",
        commands=tuple(
            CommandSpec(c.opcode, c.name, c.kind, c.register, 1000, c.shift, c.zero_ignored, c.reply)
            if c.register == "pulse_height"
            else c
            for c in V1_2.commands
        ),
    )
    item = decode(b"\xfb\x00\xf9", firmware=low_clamp)[0]
    assert item.value == 0xF900 and item.stored == 1000
    assert decode(b"\xfb\x00\xf9")[0].stored == 4095
    assert "stored as 1000" in item.describe()
    # v2: 0xF4 is a command (the sync check) and 0xFB a u8
    assert not pacing.has_payload(b"\xf4") and pacing.command_like_payload(b"\xfe\xf4") is None
    assert pacing.command_like_payload(b"\xfe\x00\xf4", V2) == 2
    assert pacing.padding_for(b"\xfb\x01") == b"\x00\x00" and pacing.padding_for(b"\xfb\x01", V2) == b"\x01"
    assert audit.describe_command(b"\xfb\x01\x00") == ("PULSE_HEIGHT", 1)
    assert audit.describe_command(b"\xfb\x01", V2) == ("STIM_MODE", 1)
    assert audit.describe_command(b"\xf4", V2) == ("SYNC_CHECK", None)
    assert audit.describe_command(b"\xf4") == ("UNKNOWN", 1)
    assert audit.describe_command(bytes([Opcode.PATTERN, 1, 2])) == ("PATTERN", [1, 2])
