"""The timed models where the upstream firmware's own C++ (the host build's differential) showed them wrong:
each test is the minimal reproduction, checked on the model alone (no compiler needed)."""

from __future__ import annotations

import dataclasses

from tactdeform_hw.emulator import HazardKind
from tactdeform_hw.emulator.hostbuild.diff import DirectLink
from tactdeform_hw.emulator.timed.model_v1_2 import TimedEmulator
from tactdeform_hw.emulator.timed.model_v2 import TimedEmulatorV2
from tactdeform_hw.emulator.timed.timing import DEFAULT_MODEL
from tactdeform_hw.protocol import firmware_math as fm
from tactdeform_hw.protocol.commands import V2_COMMANDS as c2


def test_v2_channels_past_the_stacks_outputs_deliver_nothing() -> None:
    # electrode count 255, pulse width 255, every pulse parameter at its largest, on one switching board
    # (4 HV513, 32 outputs): the firmware clocks channel 32's bit out of the chain's end
    emu = TimedEmulatorV2("compact", 1)
    emu.write(bytes.fromhex("fc ff fb ff f9 ff f7 ff"), 2000.5)
    emu.advance_to(30_000.0)
    assert emu.outputs == 32
    delivered = emu.delivered()
    assert delivered and max(r["channel"] for r in delivered) == 31
    assert {int(ch) for ch in emu.reports.pulse_table()["channel"]} <= set(range(32))
    # the parser said so when the count went past its 4 chips (no second hazard from the scans)
    beyond = [h for h in emu.hazards if h.kind is HazardKind.CHANNELS_BEYOND_HV513]
    assert len(beyond) == 1 and beyond[0].detail["channels_driven"] == 32


def test_v2_a_miscounted_stack_drives_channels_no_output_has_and_says_so() -> None:
    # one switching board really stacked, the stack reading of three: the firmware believes in 12 chips
    # (96 outputs), so a count of 40 raises nothing in the parser
    emu = TimedEmulatorV2("compact", 1, stack_reading=fm.reading_for_stack(4))
    assert emu.registers.hv513_num == 12 and emu.outputs == 32
    n = 40
    emu.write(
        c2.encode_electrode_num(n) + c2.encode_stim_mode(0) + c2.encode_pattern([50] * n),
        0.0,
    )
    emu.advance_to(40_000.0)
    assert {r["channel"] for r in emu.delivered()} == set(range(32))
    beyond = [h for h in emu.hazards if h.kind is HazardKind.CHANNELS_BEYOND_HV513]
    assert len(beyond) == 1  # from the scans, once for the stretch of such scans
    assert beyond[0].detail == {"electrode_num": n, "hv513_num": 12, "channels_driven": 32}


def test_v2_the_stimulation_timer_starts_timer_start_us_after_boot() -> None:
    # the host build's timer starts after setup(), 1010.25 us after boot; period 10 ms at power-on
    emu = TimedEmulatorV2(model=dataclasses.replace(DEFAULT_MODEL, timer_start_us=1010.25))
    emu.advance_to(40_000.0)
    assert [s.start_ns for s in emu.scans] == [11_010_250, 21_010_250, 31_010_250]
    emu.reset()  # and again after a reboot, from the end of the boot
    emu.advance_to(emu.now_us + DEFAULT_MODEL.boot_us + 10_000.0 + 1010.25)
    assert emu.scans[-1].start_ns == round((40_000.0 + DEFAULT_MODEL.boot_us + 10_000.0 + 1010.25) * 1000)


def test_v2_the_main_loop_wakes_on_ticks_shifted_by_tick_phase_us() -> None:
    # f8 b2 (sense width 178) at 2000.5 us over USB: the sleeping main loop reads it at the first tick
    # after it landed
    applied = {}
    for phase_us in (0.0, 250.0):
        emu = TimedEmulatorV2(model=dataclasses.replace(DEFAULT_MODEL, tick_phase_us=phase_us))
        emu.write(bytes.fromhex("f8 b2"), 2000.5)
        emu.advance_to(5000.0)
        applied[phase_us] = [(t, int(op), v) for t, op, v in emu.applied]
    assert applied == {0.0: [(4_000_000, 0xF8, 178)], 250.0: [(3_250_000, 0xF8, 178)]}


def test_v1_2_hv513_count_replies_after_hv513_init_clears_the_chain() -> None:
    # f5 at 2623.59 us (the differential's link: at once); the firmware replies at 4006.45 us: the call
    # (2 us + a byte's 1 us) from the tick at 3000, 1000 us of analogRead, and hv513Init's 5 + 2 x 32 pin
    # writes of 0.05 us (4 HV513 detected)
    model = dataclasses.replace(DEFAULT_MODEL, timer_start_us=1010.25)
    emu = TimedEmulator("compact", 1, link=DirectLink(), tx_link=DirectLink(), model=model)
    emu.write(bytes.fromhex("f5"), 2623.59)
    emu.advance_to(10_000.0)
    assert emu.registers.hv513_num == 4
    assert [(round(t * 1000), data) for t, data in emu.tx_log] == [(4_006_450, b"\x04")]


def test_v1_2_state_is_exact_at_a_parser_calls_granularity() -> None:
    # f8 b2 at 2000.5 us: the call at the 3000 us tick reads it and effect_us says 3006 us, when the payload
    # byte's read ends (Serial.available() and a byte read, twice: the firmware's store shows from 3005.0
    # us, when that read begins); state() shows the call's effects from its start, as the module says
    emu = TimedEmulator("compact", 1, link=DirectLink(), tx_link=DirectLink())
    emu.write(bytes.fromhex("f8 b2"), 2000.5)
    emu.advance_to(2999.999)
    assert emu.state().sense_pulse_width_us == 0
    emu.advance_to(3000.0)
    assert emu.state().sense_pulse_width_us == 178
    assert [(c.effect_us, c.value) for c in emu.commands] == [(3006.0, 178)]
