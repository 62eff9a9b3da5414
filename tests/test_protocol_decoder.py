"""The streaming decoder reads captures the way the firmware does."""

from __future__ import annotations

import pytest

from tactdeform_hw.protocol.decoder import (
    LOCKED,
    OK,
    TRUNCATED,
    UNKNOWN,
    UNREAD,
    StreamDecoder,
    decode,
    parse_hex,
)
from tactdeform_hw.protocol.firmware import FIRMWARES, FirmwareSpec


def test_decodes_a_configuration() -> None:
    items = decode(parse_hex("fc 04 fe 01 02 00 01 fb 64 00 f6 7d 00 ff f5"))
    assert [(i.name, i.value, i.status) for i in items] == [
        ("ELECTRODE_NUM", 4, OK),
        ("PATTERN", b"\x01\x02\x00\x01", OK),
        ("PULSE_HEIGHT", 100, OK),
        ("FREQUENCY", 125, OK),
        ("MEASURE", None, OK),
        ("HV513_COUNT", None, OK),
    ]
    assert [i.offset for i in items] == [0, 2, 7, 10, 13, 14]


def test_marks_unknown_truncated_locked_and_unread() -> None:
    items = decode(b"\x00\x13\xfc\x02\xfe\x01")
    assert [i.status for i in items] == [UNKNOWN, OK, TRUNCATED]
    assert items[0].raw == b"\x00\x13"
    items = decode(b"\xfe\x01\x02")
    assert [i.status for i in items] == [LOCKED, UNREAD]
    assert "LOCKS THE PARSER" in items[0].describe() and "UNREAD" in items[1].describe()


def test_flags_command_bytes_inside_a_pattern() -> None:
    items = decode(b"\xfc\x03\xfe\x01\xfb\x10")
    assert "cut short" in items[1].note


@pytest.mark.parametrize("fw", list(FIRMWARES.values()), ids=list(FIRMWARES))
@pytest.mark.parametrize(
    "text",
    ["fc 04 fe 01 02 00 01 fb 64 00 13 f6 7d", "fc 02 fe 01 21 fd 01 fb 05 f4 fa 00", "fe fc 01 fe 02 02"],
)
def test_streaming_equals_one_shot(fw: FirmwareSpec, text: str) -> None:
    """Fed byte by byte, a capture decodes as fed at once (its runs of unknown bytes are single bytes: a run
    split between feeds is reported one piece per feed)."""
    data = parse_hex(text)
    dec = StreamDecoder(firmware=fw)
    items = []
    for b in data:
        items += dec.feed(bytes([b]))
    items += dec.finish()
    whole = decode(data, firmware=fw)
    assert [i.to_dict() for i in items] == [i.to_dict() for i in whole]
    assert b"".join(i.raw for i in whole) == data


def test_parse_hex_accepts_common_spellings() -> None:
    assert parse_hex("0xfc,0x20:FE\n01") == b"\xfc\x20\xfe\x01"


def test_cli_decodes_with_the_named_firmware(capsys) -> None:  # type: ignore[no-untyped-def]
    from tactdeform_hw.cli import main

    assert main(["decode", "fc 02 fe 01 21 e8 03 fb 05 f4", "--firmware", "v2"]) == 0
    out = capsys.readouterr().out
    assert (
        "levels=[4095,1000]" in out and "STIM_MODE stim_mode=5 (stored as 2)" in out and "SYNC_CHECK" in out
    )
    assert main(["decode", "fb 00 f9"]) == 0
    assert "pulse_height=63744 (stored as 4095)" in capsys.readouterr().out
    assert main(["decode", "fa 00", "--firmware", "v2"]) == 0  # v2 discards a cut command after 2 s
    assert "within 2 s of its command byte" in capsys.readouterr().err
    assert main(["decode", "fa 00"]) == 0
    assert "within 2 s" not in capsys.readouterr().err
    assert main(["decode", "fb 00", "--firmware", "v3"]) != 0
    err = capsys.readouterr().err
    assert "--firmware 'v3'" in err and "v1.2, v2" in err and "Traceback" not in err


@pytest.mark.parametrize("fw", list(FIRMWARES.values()), ids=list(FIRMWARES))
def test_spans_are_the_commands_feed_returns(fw: FirmwareSpec) -> None:
    """``feed_spans`` (the timed emulators' ledger of what the host meant) gives, write by write, the
    offset, opcode and end of every command ``feed`` returns with an opcode, and leaves the decoder where
    ``feed`` does (its electrode count, its held-back bytes, a locked parser)."""
    import random

    rng = random.Random(7)
    alphabet = [*range(0, 4), *range(0xF0, 0x100)]  # command bytes, small counts and levels, zeros
    for _ in range(300):
        data = bytes(rng.choice(alphabet) for _ in range(rng.randint(0, 60)))
        full, lean = StreamDecoder(2, firmware=fw), StreamDecoder(2, firmware=fw)
        pos = 0
        while pos < len(data):
            n = rng.randint(1, 9)
            piece = data[pos : pos + n]
            pos += n
            want = [
                (i.offset, i.opcode, i.offset + len(i.raw)) for i in full.feed(piece) if i.opcode is not None
            ]
            assert lean.feed_spans(piece) == want
            assert lean.electrode_num == full.electrode_num
        assert [i.to_dict() for i in lean.finish()] == [i.to_dict() for i in full.finish()]
