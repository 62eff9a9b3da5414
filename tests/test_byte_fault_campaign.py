"""The exhaustive campaign's byte faults (``safety_campaign.py --exhaustive --byte-faults``,
``tools/byte_fault_campaign.py``) and the byte-indexed fault of the link (``ByteFault``): each fault strikes
the byte it names, the runs are enumerated once each with a count known before they start, the figures do
not depend on the worker count, and the judge fails a run whose wrong delivery outlasts the recovery bound
or whose lost byte the host was never told of."""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Any

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tools"))
import byte_fault_campaign as bf  # noqa: E402
import campaign_engine as engine  # noqa: E402
import exhaustive_campaign as ex  # noqa: E402
import safety_campaign as sc  # noqa: E402

from tactdeform_hw.emulator.faults import (  # noqa: E402
    CORRUPT_XOR,
    ByteFault,
    ByteFaultKind,
    FaultyLink,
)
from tactdeform_hw.emulator.timed.link import UartLink, UsbFsLink  # noqa: E402
from tactdeform_hw.errors import LimitError  # noqa: E402

FW = ("v1.2",)
#: The fault-free bytes of the depth-0 sequences on v1.2 (fresh, stimulating, stimulating and suspect),
#: on a UART and on USB: the close, and from the suspect start the fail-safe's resync.
DEPTH0_V12 = ((1, 1), (40, 40), (90, 90))
#: v1.2, stimulating, ``send_pattern(even biphasic)`` (sequence 25 of depth 1 on both firmwares).
PATTERN_SEQ = 25
DEPTH = 1
FW2 = ex.FIRMWARES


def delivered(link: FaultyLink, data: bytes, offset: int = 0) -> bytes:
    return b"".join(d.data for d in link.schedule(data, 0, offset))


@pytest.mark.parametrize(
    ("kind", "expected"),
    [
        (ByteFaultKind.LOSE, bytes([0, 1, 3, 4])),
        (ByteFaultKind.DUPLICATE, bytes([0, 1, 2, 2, 3, 4])),
        (ByteFaultKind.CORRUPT, bytes([0, 1, 2 ^ CORRUPT_XOR, 3, 4])),
        (ByteFaultKind.TAIL_LOSS, bytes([0, 1, 3, 4])),  # a UART delivery is one byte: its tail is itself
    ],
)
def test_a_byte_fault_strikes_the_byte_it_names_once_on_a_uart(kind: ByteFaultKind, expected: bytes) -> None:
    link = FaultyLink(UartLink())
    link.add_byte_fault(ByteFault(kind, 12))  # the host's byte 12: the third of a write that starts at 10
    assert delivered(link, bytes(range(5)), 10) == expected
    assert [(f.kind, f.host_offset) for f in link.injected] == [(kind, 12)]
    assert delivered(link, bytes(range(5)), 15) == bytes(range(5))  # struck once


def test_a_tail_loss_keeps_the_packets_head_and_the_other_packets() -> None:
    link = FaultyLink(UsbFsLink())
    link.add_byte_fault(ByteFault("tail_loss", 64 + 10))  # second packet, after its 10th byte
    data = bytes(i % 200 for i in range(150))
    assert delivered(link, data) == data[:74] + data[128:]
    (f,) = link.injected
    assert f.detail["kept"] == 10 and f.detail["bytes"] == 54


def test_a_byte_fault_names_its_byte_and_kind() -> None:
    with pytest.raises(LimitError, match="host_index"):
        ByteFault(ByteFaultKind.LOSE, -1)
    with pytest.raises(ValueError, match="'melt'"):
        ByteFault("melt", 3)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="on usb the kind is one of tail_loss"):
        bf.parse_spec("usb:lose:3")


def test_the_runs_of_depth_0_are_counted_and_enumerated_once() -> None:
    table = tuple(bf.count_chunk(0, FW, bf.PLAIN, 0, ex.count(0, FW)).written[i] for i in range(3))
    assert table == DEPTH0_V12
    total = sum(bf.runs_per_sequence(w) for w in table)
    assert total == 3 * 131 + 131 == 524
    runs = [bf.decode_run(i, table) for i in range(total)]
    expected = {
        bf.Run(seq, link, kind, byte)
        for seq, written in enumerate(table)
        for link, n in zip(bf.LINKS, written, strict=True)
        for kind in bf.KINDS[link]
        for byte in range(n)
    }
    assert len(set(runs)) == total and set(runs) == expected
    assert runs[0] == bf.Run(0, "uart", ByteFaultKind.LOSE, 0)
    assert runs[-1] == bf.Run(2, "usb", ByteFaultKind.TAIL_LOSS, 89)
    with pytest.raises(IndexError, match="0 to 523"):
        bf.decode_run(total, table)


def test_a_fault_past_the_last_byte_fails_as_not_struck() -> None:
    r = bf.run_one(bf.Run(0, "uart", ByteFaultKind.LOSE, 1), 0, FW)  # the fresh start writes 1 byte
    assert bf.failed(r) and "NOT STRUCK: byte 1 of 1 written" in bf.why(r)


# --- the judge passes the driver and can fail ---------------------------------------------------------------

#: A lost byte late in the closing of the biphasic pattern: a pulse above the cap follows (v1.2's plain
#: encoding), 22.4 ms after the fault, within the recovery bound.
WRONG = bf.Run(PATTERN_SEQ, "uart", ByteFaultKind.LOSE, 71)
#: The first byte of that sequence lost: the host is told (nothing else is judged).
LOST = bf.Run(PATTERN_SEQ, "uart", ByteFaultKind.LOSE, 0)


def test_a_wrong_delivery_within_the_bound_passes_and_fails_past_a_broken_bound(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    r = bf.run_one(WRONG, DEPTH, FW2)
    assert r.first_violation is not None and r.first_violation["why"] == "over_limit"
    assert 0 < r.wrong_after_fault_s < r.recovery_bound_s and not bf.failed(r)
    monkeypatch.setattr(bf.ByteFaultSession, "recovery_bound_s", lambda self: 0.005)
    r = bf.run_one(WRONG, DEPTH, FW2)
    assert bf.failed(r) and "wrong deliveries past the recovery bound" in bf.why(r)


def erase_reports(self: bf.ByteFaultSession) -> sc.SessionResult:
    """The judge of a host that was told nothing: every error, failed proof, recovery, proof and span
    without proof erased before the verdict."""
    self.notices.clear()
    self.refused_spans.clear()
    self.failsafe.events.clear()
    for d in self.devices:
        d.transitions.clear()
        d.proofs.clear()
        d.unproved_spans = list  # type: ignore[method-assign]
    return sc.Session.judge(self)


def test_a_lost_byte_the_host_is_not_told_of_fails(monkeypatch: pytest.MonkeyPatch) -> None:
    r = bf.run_one(LOST, DEPTH, FW2)
    assert r.faults == ["lose"] and not bf.failed(r) and r.unreported_lost_bytes == 0
    monkeypatch.setattr(bf.ByteFaultSession, "judge", erase_reports)
    r = bf.run_one(LOST, DEPTH, FW2)
    assert bf.failed(r) and r.unreported_lost_bytes == 1 and "1 bytes lost unreported" in bf.why(r)
    # a judge that counts only the receive queue's losses would not see the byte the link lost
    monkeypatch.setattr(bf.ByteFaultSession, "lost_bytes_at", sc.Session.lost_bytes_at)
    assert not bf.failed(bf.run_one(LOST, DEPTH, FW2))


def failing_tally(monkeypatch: pytest.MonkeyPatch) -> dict[str, Any]:
    monkeypatch.setattr(bf.ByteFaultSession, "recovery_bound_s", lambda self: 0.005)
    table = ((74, 74),) * (PATTERN_SEQ + 1)  # only the pattern sequence's runs are asked for
    first = (PATTERN_SEQ) * bf.runs_per_sequence((74, 74)) + 70  # the UART's lost bytes 70 to 72
    result: dict[str, Any] = bf.tally_chunk(DEPTH, FW2, table, bf.PLAIN, first, 3).summary()
    return result


def test_a_failed_run_is_listed_with_the_command_that_replays_it(monkeypatch: pytest.MonkeyPatch) -> None:
    s = failing_tally(monkeypatch)
    assert s["faulty_runs"] == 3 and s["failed_runs"] >= 1
    f = s["failures"][0]
    assert f["fault"] == "uart:lose:71"
    assert f["reproduce"] == (
        "python tools/safety_campaign.py --exhaustive --depth 1 --firmware both --only 25 "
        "--byte-fault uart:lose:71"
    )
    assert sc.main(["--exhaustive", "--depth", "1", "--only", "25", "--byte-fault", "uart:lose:71"]) == 1


def test_the_figures_are_the_same_on_one_and_two_workers() -> None:
    table = DEPTH0_V12
    j = bf.job(0, FW, table, chunk=3)
    # the runs of the stimulating start's first bytes and the suspect start's last ones
    slices = [engine.Job(j.module, j.function, j.args, 6, first=4 * 1 + 2, chunk=2, unit="runs")]
    slices.append(engine.Job(j.module, j.function, j.args, 5, first=j.total - 5, chunk=2, unit="runs"))
    for job in slices:
        one = engine.run(job, jobs=1).summary()
        two = engine.run(job, jobs=2).summary()
        assert one == two and one["faulty_runs"] == job.total and one["failed_runs"] == 0
        assert one["pulses"] > 0


def test_a_slice_of_runs_names_its_bounds() -> None:
    assert bf.parse_runs("15648:41208") == (15648, 41208)
    for bad in ("5:3", "5", "a:7", "-1:4"):
        with pytest.raises(ValueError, match="FIRST:END with 0 <= FIRST < END"):
            bf.parse_runs(bad)
    assert bf.start_ranges(DEPTH0_V12, 0, FW) == [
        "v1.2 fresh: runs 0:4",
        "v1.2 stimulating: runs 4:164",
        "v1.2 stimulating_suspect: runs 164:524",
    ]
    j = bf.job(0, FW, DEPTH0_V12, runs=(4, 164))
    assert (j.first, j.total) == (4, 160)


# --- a sample of the runs -----------------------------------------------------------------------------------


def test_a_sampled_run_is_a_run_of_the_enumeration_drawn_the_same_on_any_chunking() -> None:
    """Each sample is one of the enumeration's runs (its sequence's byte counted by the fault-free pass the
    enumeration makes), and the same whichever chunk, worker or engine draws it."""
    table = DEPTH0_V12
    ends = [sum(bf.runs_per_sequence(w) for w in table[: k + 1]) for k in range(len(table))]
    drawn = [bf.sample_run(i, 5, 0, FW) for i in range(12)]
    for run, runs in drawn:
        first = ends[run.sequence - 1] if run.sequence else 0
        in_sequence = [bf.decode_run(k, table, ends) for k in range(first, ends[run.sequence])]
        assert run in in_sequence and runs == len(in_sequence)
    assert len({r.sequence for r, _ in drawn}) == 3  # each start drawn
    assert drawn == [bf.sample_run(i, 5, 0, FW) for i in range(12)]
    assert drawn != [bf.sample_run(i, 6, 0, FW) for i in range(12)]
    j = engine.Job("byte_fault_campaign", "sample_chunk", (0, FW, bf.PLAIN, 5), 8, chunk=3, unit="runs")
    t1, t2 = engine.run(j, jobs=1), engine.run(j, jobs=2)
    one, two = t1.summary(), t2.summary()
    assert one == two and one["faulty_runs"] == 8 and one["failed_runs"] == 0 and one["pulses"] > 0
    assert t1.sequence_runs == t2.sequence_runs == sum(bf.sample_run(i, 5, 0, FW)[1] for i in range(8))


def test_a_sample_states_the_share_it_rules_out_and_replays_each_failure(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    assert bf.upper_bound_95(0, 1) == pytest.approx(0.95)
    assert bf.upper_bound_95(0, 100_000) == pytest.approx(2.996e-5, rel=1e-3)
    assert bf.upper_bound_95(1, 100_000) is None
    assert sc.main(["--exhaustive", "--depth", "0", "--firmware", "v1.2", "--byte-faults", "--sample", "4",
                    "--seed", "3", "--json"]) == 0  # fmt: skip
    out = json.loads(capsys.readouterr().out)
    assert out["mode"] == "sampled byte faults" and out["sampled_runs"] == out["faulty_runs"] == 4
    assert out["failing_share_below_95"] == pytest.approx(1 - 0.05**0.25, rel=1e-3)
    # the enumeration's size, estimated from the sequences drawn (depth 0 on v1.2: 524 runs, counted)
    drawn = [bf.sample_run(i, 3, 0, FW)[1] for i in range(4)]
    assert out["runs_in_enumeration_estimated"] == round(sum(drawn) / 4 * 3)
    assert set(drawn) <= {bf.runs_per_sequence(w) for w in DEPTH0_V12}
    # a run the judge fails is listed with the one command that replays it
    monkeypatch.setattr(bf, "failed", lambda r: True)
    monkeypatch.setattr(bf, "why", lambda r: "JUDGED FAILED")
    assert sc.main(["--exhaustive", "--depth", "0", "--firmware", "v1.2", "--byte-faults", "--sample", "2",
                    "--seed", "3", "--json"]) == 1  # fmt: skip
    captured = capsys.readouterr()
    out = json.loads(captured.out)
    assert out["failed_runs"] == 2 and out["failing_share_below_95"] is None
    run, _ = bf.sample_run(0, 3, 0, FW)
    assert f"--only {run.sequence} --byte-fault {run.spec()}" in captured.err


def test_a_tail_lost_from_a_cover_pattern_is_caught_by_the_whole_measure_reply() -> None:
    """Found by the depth-4 sample (seed 1): from the stimulating start, ``configure(1)``'s 32-zero cover
    pattern loses its packet's tail, so the pattern swallows the count 1 and the bytes after it and
    channel 15 is left stimulating at the cap on a board that still scans 32 channels.  The proof's
    0xFF is answered with 64 bytes where the host expects 2: read whole, it is reported and recovered
    within the bound; read to 2 bytes, it passed and the board stimulated past its close."""
    r = bf.run_one(bf.Run(151261, "usb", ByteFaultKind.TAIL_LOSS, 17), 4, FW)
    assert not bf.failed(r), bf.why(r)
    assert any("LongReplyError" in e for e in r.errors)


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--sample", "5"], "--sample applies to --exhaustive --byte-faults"),
        (["--exhaustive", "--byte-faults", "--sample", "0"], "--sample must be at least 1 (got 0)"),
        (["--exhaustive", "--byte-faults", "--sample", "5", "--runs", "0:9"], "give it or --runs, not both"),
    ],
)
def test_a_sample_asked_for_wrongly_is_refused_naming_the_flag(
    args: list[str], message: str, capsys: pytest.CaptureFixture[str]
) -> None:
    with pytest.raises(SystemExit) as exc:
        sc.main(args)
    assert exc.value.code == 2 and message in capsys.readouterr().err


# --- the robust encoding: a lost byte above the limit fails the run -----------------------------------------

#: v1.2 from the stimulating start, ``configure(1)``: under the plain encoding the first byte of its zero
#: height ``FB 00 00`` lost gives one scan at the DAC's full scale (code 4095, 40 950 uA) on the 16
#: stimulating channels of the 32 the board still scans.
FULL_SCALE = bf.Run(21, "uart", ByteFaultKind.LOSE, 2)
ROBUST = bf.Mode("robust", ("uart:lose",))


def test_the_plain_encoding_passes_a_full_scale_pulse_after_a_lost_byte_within_the_bound() -> None:
    r = bf.run_one(FULL_SCALE, DEPTH, FW)
    assert r.max_stim_ua == 40950.0 and r.over_limit == 16 and not bf.failed(r)


def test_under_the_robust_encoding_a_lost_byte_above_the_limit_fails_the_run(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    r = bf.run_one(FULL_SCALE, DEPTH, FW, ROBUST)  # the same byte of the robust encoding's stream
    assert r.robust and r.over_limit == 0 and not bf.failed(r)
    # a run that claims the robust encoding while its devices use the plain one: the pulse fails it
    monkeypatch.setattr(
        bf, "_session", lambda fw, start, seq, link, robust: bf.ByteFaultSession(seq, fw, start, link)
    )
    r = bf.run_one(FULL_SCALE, DEPTH, FW, ROBUST)
    assert bf.failed(r) and r.wrong_after_fault_s < r.recovery_bound_s
    assert "LOST BYTE ABOVE THE LIMIT: 16 pulses above 1500 uA under the robust encoding" in bf.why(r)


def test_v2_a_refresh_after_a_cover_a_lost_byte_shifted_writes_its_zeros_before_the_mode() -> None:
    """From the stimulating start, the watchdog's cover (``FB 02``, zeros, ``FB 00``) loses a zero: the
    shifted pattern takes ``FB`` as its last height (clamped to 4095) and the mode stays 2 at sense height
    0, where it delivers nothing.  The host believes zeros in mode 0, so the fail-safe's refresh writes
    them again: with the mode first, a scan between the two ran the shifted heights in mode 0 (one pulse
    of 40 950 uA, under the robust encoding); zeros first, nothing above the cap."""
    robust_lose = bf.Mode("robust", ("uart:lose",))
    for byte in (75, 88, 94):
        r = bf.run_one(bf.Run(39, "uart", ByteFaultKind.LOSE, byte), DEPTH, ("v2",), robust_lose)
        assert not bf.failed(r) and r.over_limit == 0, bf.why(r)


def test_a_robust_enumeration_numbers_only_its_kinds_and_replays_with_its_encoding() -> None:
    assert bf.parse_kinds("usb:tail_loss, uart:lose") == ("uart:lose", "usb:tail_loss")
    for bad in ("", "uart:melt", "usb:lose"):
        with pytest.raises(ValueError, match="--kinds"):
            bf.parse_kinds(bad)
    table = ((3, 5),)
    assert bf.runs_per_sequence(table[0], ROBUST) == 3
    assert [bf.decode_run(i, table, mode=ROBUST).spec() for i in range(3)] == [
        "uart:lose:0",
        "uart:lose:1",
        "uart:lose:2",
    ]
    assert bf.reproduce(FULL_SCALE, DEPTH, FW, ROBUST) == (
        "python tools/safety_campaign.py --exhaustive --depth 1 --firmware v1.2 --only 21 "
        "--encoding robust --byte-fault uart:lose:2"
    )
    assert bf.count_chunk(0, FW, ROBUST, 0, 1).written == {0: (1, 0)}  # USB not run: no kind strikes it


#: v2 from the stimulating start, ``send_pattern(even biphasic)``, the robust encoding's byte 78 lost: a
#: byte inside the pattern's heights.  With the pattern padded as a lone one, the loss shifts every later
#: height by a byte, the firmware clamps the value formed to 4095, and the next scans deliver it (40 950 uA,
#: 30 pulses, 7.4 ms after the loss; 60 of 27 245 runs of the whole v2 enumeration).
V2_ROBUST_HOLE = bf.Run(PATTERN_SEQ, "uart", ByteFaultKind.LOSE, 78)
V2 = ("v2",)


def test_under_the_robust_encoding_no_lost_byte_of_a_v2_pattern_raises_a_current() -> None:
    """Every byte of v2's ``send_pattern(even biphasic)`` writes lost, one run each: the cover's pattern is
    unpadded, so a shifted pattern takes the mode's ``FB`` and the mode stays 2 (no current)."""
    uart_bytes = bf.count_chunk(DEPTH, V2, ROBUST, PATTERN_SEQ, 1).written[PATTERN_SEQ][0]
    assert uart_bytes > 100
    bad = []
    for byte in range(uart_bytes):
        r = bf.run_one(bf.Run(PATTERN_SEQ, "uart", ByteFaultKind.LOSE, byte), DEPTH, V2, ROBUST)
        assert r.robust
        if r.over_limit or bf.failed(r):
            bad.append((byte, r.over_limit, bf.why(r)))
    assert bad == []


def test_a_v2_pattern_padded_before_the_mode_delivers_the_shifted_heights(monkeypatch: Any) -> None:
    """The same lost byte with the cover's pattern padded as a lone pattern is: the shifted pattern is
    complete before ``FB mode``, which then applies, and its clamped height is delivered (the rule of
    :func:`~tactdeform_hw.device.driver.pacing.paddings` is what the test above holds)."""
    from tactdeform_hw.device.driver import pacing, wire

    def padded(commands: Any, firmware: Any = pacing.DEFAULT_FIRMWARE) -> list[bytes]:
        return [pacing.padding_for(c, firmware) for c in commands]

    monkeypatch.setattr(pacing, "paddings", padded)
    monkeypatch.setattr(wire, "paddings", padded)
    r = bf.run_one(V2_ROBUST_HOLE, DEPTH, V2, ROBUST)
    assert r.over_limit > 0 and bf.failed(r)
    assert any(e.startswith(bf.ROBUST_LOSS) for e in r.errors)
