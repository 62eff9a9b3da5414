"""Firmware in the loop: a small Arduino-style firmware (tests/data/firmware_tiny) built on the host
against the package's shim, and driven in virtual time.

Times are exact: the shim keeps integer nanoseconds and every call's cost comes from the TimingModel, so
each expected figure below is the sum of the costs the firmware's code path incurs."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest

from tactdeform_hw.emulator.hostbuild import build, find_compiler
from tactdeform_hw.emulator.hostbuild.emulator import HostBuildEmulator
from tactdeform_hw.emulator.hostbuild.statemap import StateMap
from tactdeform_hw.emulator.timed.timing import DEFAULT_MODEL
from tactdeform_hw.errors import ConfigurationError, FirmwareBuildError

TINY = Path(__file__).parent / "data" / "firmware_tiny"
MAP = StateMap.from_toml(TINY / "hostbuild_state.toml")
M = DEFAULT_MODEL

try:
    find_compiler()
    HAVE_CXX = True
except FirmwareBuildError as exc:
    HAVE_CXX = False
    NO_CXX = str(exc)

pytestmark = pytest.mark.skipif(not HAVE_CXX, reason="no C++ compiler on PATH (c++, g++, clang++ or $CXX)")

# The interrupt: entry, pin up, CS down, one SPI exchange, CS up, pin down.
ISR_NS = M.isr_entry_ns + 4 * M.gpio_ns + M.spi_ns


@pytest.fixture(scope="module")
def cache(tmp_path_factory: pytest.TempPathFactory) -> Path:
    where = tmp_path_factory.mktemp("fwcache")
    build(TINY, state_map=MAP, cache=where)  # the one cold build of this module
    return where


def tiny(cache: Path, **kw: object) -> HostBuildEmulator:
    return HostBuildEmulator(TINY, state_map=MAP, cache=cache, **kw)  # type: ignore[arg-type]


def us(ns: int) -> float:
    return ns / 1000.0


# --- the build ----------------------------------------------------------------------------------------------


def test_second_build_is_a_cache_hit(cache: Path) -> None:
    first = build(TINY, state_map=MAP, cache=cache)
    again = build(TINY, state_map=MAP, cache=cache)
    assert first.cached and again.cached
    assert again.library == first.library and again.library.is_file()


def test_a_changed_source_is_rebuilt(cache: Path, tmp_path: Path) -> None:
    tree = tmp_path / "fw"
    shutil.copytree(TINY, tree)
    before = build(tree, state_map=MAP, cache=cache)
    assert before.cached  # same content, another folder: the same binary
    src = tree / "lib" / "Tiny" / "tiny.cpp"
    src.write_text(src.read_text().replace("period_us = 700", "period_us = 900"))
    after = build(tree, state_map=MAP, cache=cache)
    assert not after.cached and after.key != before.key
    emu = HostBuildEmulator(tree, state_map=MAP, cache=cache)
    emu.advance_to(1000)
    assert [e for e, _ in emu.scans()] == [900.0]


def test_compile_error_names_the_file_and_line(cache: Path, tmp_path: Path) -> None:
    tree = tmp_path / "fw"
    shutil.copytree(TINY, tree)
    src = tree / "lib" / "Tiny" / "tiny.cpp"
    lines = src.read_text().splitlines()
    lines.insert(9, "int broken = ;")  # becomes line 10
    src.write_text("\n".join(lines) + "\n")
    with pytest.raises(FirmwareBuildError) as info:
        build(tree, state_map=MAP, cache=cache)
    assert info.value.file == "lib/Tiny/tiny.cpp" and info.value.line == 10
    assert "lib/Tiny/tiny.cpp:10: error:" in str(info.value)


def test_undefined_function_is_a_build_error_naming_it(cache: Path, tmp_path: Path) -> None:
    tree = tmp_path / "fw"
    shutil.copytree(TINY, tree)
    main = tree / "src" / "main.cpp"
    main.write_text(
        main.read_text()
        .replace("tinyPoll();", "tinyPoll();\n    notDefinedAnywhere();")
        .replace('#include "tiny.h"', '#include "tiny.h"\nvoid notDefinedAnywhere();')
    )
    with pytest.raises(FirmwareBuildError, match="undefined symbol.*notDefinedAnywhere"):
        build(tree, state_map=MAP, cache=cache)


def test_state_map_naming_no_variable_names_the_register(cache: Path) -> None:
    bad = StateMap(unit="lib/Tiny/tiny.cpp", registers={"isr_count": "isr_count", "gain": "no_such_var"})
    with pytest.raises(FirmwareBuildError, match="register 'gain'"):
        build(TINY, state_map=bad, cache=cache)


def test_missing_compiler_says_what_to_install(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    monkeypatch.setenv("PATH", str(tmp_path))
    monkeypatch.delenv("CXX", raising=False)
    with pytest.raises(
        FirmwareBuildError, match="needs a C\\+\\+ compiler.*c\\+\\+, g\\+\\+, clang\\+\\+"
    ) as info:
        find_compiler()
    assert "apt install g++" in str(info.value) or "xcode-select" in str(info.value)


# --- virtual time -------------------------------------------------------------------------------------------


def test_interrupt_runs_on_its_period_and_costs_what_the_model_says(cache: Path) -> None:
    emu = tiny(cache)
    emu.advance_to(2500)
    assert emu.scans() == [(t, t + us(ISR_NS)) for t in (700.0, 1400.0, 2100.0)]
    assert emu.state()["isr_count"] == 3


def test_costs_come_from_the_timing_model(cache: Path) -> None:
    model = M.with_(spi_exchange_us=10.0, isr_entry_us=1.0)
    emu = tiny(cache, timing=model)
    emu.advance_to(800)
    assert emu.scans() == [(700.0, 700.0 + 1.0 + 4 * 0.05 + 10.0)]


def test_gpio_and_dac_events_in_the_golden_conventions(cache: Path) -> None:
    emu = tiny(cache)
    emu.write(b"V" + (1234).to_bytes(2, "little"), at_us=100)  # parsed at the 1000 µs tick
    emu.advance_to(1500)
    t = 1_400_000 + M.isr_entry_ns
    g = M.gpio_ns
    assert emu.events(since_us=1400) == [
        [us(t + g), "GPIO", 5, 1],
        [us(t + 2 * g), "GPIO", 40, 0],
        [us(t + 2 * g + M.dac_at_ns), "DAC", "DAC", 1234],
        [us(t + 3 * g + M.spi_ns), "GPIO", 40, 1],
        [us(t + 4 * g + M.spi_ns), "GPIO", 5, 0],
    ]


def test_new_period_takes_effect_through_the_parser(cache: Path) -> None:
    emu = tiny(cache)
    emu.write(b"P" + (250).to_bytes(2, "little"), at_us=100)
    emu.advance_to(1600)
    # the loop reads it at 1000 µs (its first RTOS tick); the counter, restarted at 700, already passed 250
    # ticks, so the re-enabled alarm fires at once; then every 250 µs from that reload
    entries = [e for e, _ in emu.scans()]
    assert emu.state()["period_us"] == 250 and emu.state()["timer_alarm_ticks"] == 250
    t_set = 1000 + us(2 * M.call_ns + 3 * M.byte_ns)  # available, read 'P', available, read 2 bytes
    assert entries[0] == 700.0 and entries[1] == t_set
    assert entries[2:] == [t_set + 250.0 * k for k in (1, 2)]


def test_reply_after_the_loop_wakes_on_its_tick(cache: Path) -> None:
    emu = tiny(cache)
    emu.write(b"EA", at_us=2500)
    emu.advance_to(3500)
    # the loop sleeps vTaskDelay(1): it wakes at 3000 µs, then available/read/available/read
    assert emu.tx_log == [(3000 + us(2 * M.call_ns + 2 * M.byte_ns), b"B")]
    assert emu.read() == b"B" and emu.read() == b""


def test_busy_wait_on_timer_read_is_exact_and_preempted_by_the_interrupt(cache: Path) -> None:
    emu = tiny(cache)
    emu.write(b"W\xff", at_us=8500)
    emu.advance_to(9500)
    start = 9000 + us(2 * M.call_ns + 2 * M.byte_ns)  # timerRestart here
    assert emu.tx_log == [(start + 255.0, b"w")]  # the counter ran on through the interrupt
    assert (9100.0, 9100.0 + us(ISR_NS)) in emu.scans()  # which fell inside the wait


def test_an_analog_read_is_pre_empted_at_the_alarm_and_finishes_after_the_interrupt(cache: Path) -> None:
    """An analogRead() (``hv513_detect_us / 50``, 20 µs) is work the interrupt pre-empts where its alarm
    falls, as the chip takes it, not at the firmware's next call: 255 reads from 4006 µs (the 4000 µs tick:
    available, read 'A', available, read n) put the alarm of 4200 µs inside the 10th, whose handler runs at
    4200 µs exactly; the rest of each read follows its handler, so the reply comes 255 reads and one
    handler per alarm of the stretch after the start."""
    emu = tiny(cache)
    emu.write(b"A\xff", at_us=3500.5)
    emu.advance_to(10_000)
    start = 4000 + us(2 * M.call_ns + 2 * M.byte_ns)
    assert (4200.0, 4200.0 + us(ISR_NS)) in emu.scans()
    handlers = [e for e, _ in emu.scans() if e >= start]
    assert handlers == [700.0 * k for k in range(6, 15)]  # 4200 ... 9800 µs, each on its alarm
    # 255 reads of 20 µs from 4006 µs end at 9106 µs plus the 8 handlers of 4200 ... 9100 µs
    assert emu.tx_log == [(start + us(255 * (M.hv513_detect_ns // 50) + 8 * ISR_NS), b"a")]


def test_a_serial_read_is_pre_empted_at_the_alarm_before_the_firmware_stores_its_bytes(cache: Path) -> None:
    """Serial calls are work the interrupt pre-empts where its alarm falls, as the chip takes it: 'V' and
    the first byte of its u16 wait at the 4000 µs tick; readU16() polls Serial.available() (2 µs) from
    4003 µs until the second byte, arriving at 4196 µs, is seen at 4197 µs; its Serial.read(b, 2) runs from
    4199 to 4201 µs, so the handler of the 4200 µs alarm runs at 4200 µs exactly, inside it, and sends the
    DAC code from before ('V' stores the code after the read returns); the next handler sends the new
    one."""
    emu = tiny(cache)
    emu.write(b"V\x10", at_us=3500.5)
    emu.write(b"\x00", at_us=4196.0)
    emu.advance_to(5000)
    entries = [e.t_us for e in emu.shim_events() if e.kind == "ISR_ENTER" and e.t_us > 4000]
    assert entries == [4200.0, 4900.0]
    sent = [e.b >> 2 for e in emu.shim_events() if e.kind == "SPI" and e.t_us > 4000]
    assert sent == [0, 0x10]


def test_a_function_local_static_is_read_through_the_symbol_table(cache: Path) -> None:
    """``tinyPoll()::polls`` (a function-local static no expression can name) counts the loop's polls: one
    per 1 ms tick from the first, read from the library's symbol table in each instance's own copy."""
    first, second = tiny(cache), tiny(cache)
    first.advance_to(5500)
    second.advance_to(2500)
    assert (first.state()["polls"], second.state()["polls"]) == (6, 3)  # ticks 0 ... 5000, 0 ... 2000


def test_a_local_static_the_firmware_does_not_have_is_named_in_the_error(cache: Path) -> None:
    bad = StateMap(unit=MAP.unit, registers={**MAP.registers, "ghost": "tinyPoll()::ghost"}, name="bad map")
    with pytest.raises(ConfigurationError, match=r"'ghost'.*tinyPoll\(\)::ghost"):
        HostBuildEmulator(TINY, state_map=bad, cache=cache)


def test_interrupt_count_reply(cache: Path) -> None:
    emu = tiny(cache)
    emu.write(b"C", at_us=4500)
    emu.advance_to(5500)
    assert emu.read() == (7).to_bytes(4, "little")  # read at the 5000 µs tick: 700, 1400 … 4900


def test_receive_queue_overflow_drops_the_rest_of_each_packet(cache: Path) -> None:
    emu = tiny(cache)
    emu.advance_to(1500)  # the firmware asked for a 128-byte queue in setup()
    assert emu.state()["rx_capacity"] == 128
    emu.write(b"E\x01", at_us=1500)
    emu.write(bytes(300), at_us=1500)  # 2 + 300 bytes at once: 64-byte packets
    emu.advance_to(1500)
    st = emu.state()
    assert st["rx_pending"] == 128 and st["rx_dropped"] == 302 - 128
    # packets: host bytes [0,2) and [2,66) [66,130) [130,194) [194,258) [258,302); the third breaks at 128
    assert [(d.host_offset, d.count) for d in emu.rx_drops] == [(128, 2), (130, 64), (194, 64), (258, 44)]
    emu.advance_to(2500)
    assert emu.read() == b"\x02"  # what did fit is served in order


def test_available_sees_only_bytes_that_have_arrived(cache: Path) -> None:
    emu = tiny(cache)
    emu.write(b"P" + (65535).to_bytes(2, "little"), at_us=100)  # no interrupt in the window below
    emu.write(b"E", at_us=1500)
    emu.write(b"\x10", at_us=4200.5)  # the parser spins on available() until this byte is there
    emu.advance_to(4100)
    assert emu.read() == b""
    emu.advance_to(4300)
    # at the 2000 µs tick: available, read 'E'; then available() polls every call_ns; the first poll at or
    # after the byte's arrival sees it, one more read, the reply
    first_poll = 2_000_000 + M.call_ns + M.byte_ns
    polls = -(-(4_200_500 - first_poll) // M.call_ns)
    assert emu.tx_log == [(us(first_poll + polls * M.call_ns + M.call_ns + M.byte_ns), b"\x11")]


def test_two_instances_do_not_share_the_firmware_globals(cache: Path) -> None:
    a = tiny(cache)
    b = tiny(cache)
    a.write(b"V" + (77).to_bytes(2, "little"), at_us=0)
    a.advance_to(3000)
    b.advance_to(1000)
    assert a.state()["dac_code"] == 77 and b.state()["dac_code"] == 0
    assert a.state()["isr_count"] == 4 and b.state()["isr_count"] == 1
    assert b.now_us == 1000.0 and a.now_us == 3000.0


def _mapped_copies() -> int:
    """Private firmware copies mapped into this process (each instance dlopens its own)."""
    maps = Path("/proc/self/maps").read_text()
    return len({line.split()[-2] for line in maps.splitlines() if "tactdeform-fw-" in line})


@pytest.mark.skipif(not Path("/proc/self/maps").is_file(), reason="needs /proc/self/maps (Linux)")
def test_close_unloads_the_firmware_copy_and_a_collected_instance_is_unloaded_too(cache: Path) -> None:
    before = _mapped_copies()
    emu = tiny(cache)
    emu.write(b"E\x05", at_us=0)
    emu.advance_to(2500)
    assert _mapped_copies() == before + 1
    emu.close()
    assert _mapped_copies() == before
    assert emu.read() == b"\x06"  # what was already taken stays readable
    with pytest.raises(FirmwareBuildError, match="closed"):
        emu.advance_to(3000)
    with pytest.raises(FirmwareBuildError, match="closed"):
        emu.state()
    emu.close()  # twice is harmless
    with tiny(cache) as other:
        other.advance_to(1000)
        assert _mapped_copies() == before + 1
    assert _mapped_copies() == before
    tiny(cache).advance_to(1000)  # dropped at once: collected, unloaded
    assert _mapped_copies() == before


def test_state_reads_static_variables_through_the_map(cache: Path) -> None:
    emu = tiny(cache)
    emu.write(b"C" + b"E\x05", at_us=0)
    emu.advance_to(2500)
    assert emu.state()["history"] == [ord("E"), ord("C"), 0, 0]


def test_a_loop_that_lets_no_time_pass_is_reported(cache: Path) -> None:
    emu = tiny(cache, stall_calls=10_000)
    emu.write(b"H", at_us=0)
    with pytest.raises(FirmwareBuildError, match="10000 shim calls.*without time passing"):
        emu.advance_to(2000)


def test_watched_registers_are_read_at_every_interrupt_entry(cache: Path) -> None:
    """A watched register is read when each handler run begins, however seldom Python looks: the readings
    carry the entries' own times, and a value the main loop changed between two entries is seen at the
    second."""
    emu = tiny(cache)
    emu.watch_at_isr("isr_count")
    emu.watch_at_isr("dac_code")
    emu.write(b"V" + (321).to_bytes(2, "little"), at_us=2500)
    emu.advance_to(5000)  # one step across several interrupts and the command
    entries = [a for a, _ in emu.scans()]
    counts = [s for s in emu.isr_samples() if s.register == "isr_count"]
    assert [s.t_us for s in counts] == entries  # it changes at every run
    assert [s.value for s in counts] == list(range(len(entries)))
    codes = [(s.t_us, s.value) for s in emu.isr_samples() if s.register == "dac_code"]
    assert codes[0] == (entries[0], 0)
    assert len(codes) == 2 and codes[1][1] == 321
    # the loop reads the command on its next RTOS tick (3000 us): the first run after that one uses it
    assert codes[1][0] == min(t for t in entries if t > 3000) == 3500


def test_watching_a_register_the_state_map_does_not_name_is_refused(cache: Path) -> None:
    emu = tiny(cache)
    with pytest.raises(ConfigurationError, match="'pulse_height' is not in the state map.*isr_count"):
        emu.watch_at_isr("pulse_height")


def test_a_timed_host_build_keeps_a_bounded_event_record(cache: Path) -> None:
    from tactdeform_hw.emulator.hostbuild.timed import HostBuildTimedModel

    model = HostBuildTimedModel(TINY, state_map=MAP, cache=cache, event_history_us=10_000)
    for t_us in range(1000, 100_001, 1000):
        model.advance_to(t_us)
    kept = model.host.shim_events()
    assert kept and kept[0].t_us >= 100_000 - 2 * 10_000  # trimmed every 10 ms to the last 10 ms
    assert len(model.scans()) < 40  # of the 142 interrupt runs (700 us period)
