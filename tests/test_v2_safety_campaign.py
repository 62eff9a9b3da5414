"""The safety campaign on firmware v2 (``tools/safety_campaign.py --firmware v2``): random sessions of
public ``Device`` calls on the timed v2 model, judged per electrode on the pulses it delivered, and the v2
recovery bound (the sync check, then the firmware's 2 s command timeout) the fault verdict rests on."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

from tactdeform_hw.device.driver.base import LinkState
from tactdeform_hw.device.driver.config import StimConfig
from tactdeform_hw.device.driver.v2 import COMMAND_TIMEOUT_S
from tactdeform_hw.device.safety.failsafe import FailSafe
from tactdeform_hw.errors import TactDeformError
from tactdeform_hw.protocol.commands import V2_COMMANDS as c2

from .safety_helpers import CAMPAIGN_CALLS, OPEN_DEFECTS, assert_fault_free, assert_fault_free_but_for
from .test_v2_driver import _timed_v2

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tools"))
import safety_campaign as sc  # noqa: E402

#: Sessions the suite runs (a few seconds on one core).
SESSIONS = 150
FAULT_SESSIONS = 40


@pytest.fixture(scope="module")
def fault_free() -> list[sc.SessionResult]:
    return sc.run_campaign(SESSIONS, seed=0, firmware="v2")


def test_fault_free_v2_campaign_delivers_nothing_above_any_electrodes_limit(
    fault_free: list[sc.SessionResult],
) -> None:
    """Every check of the verdict, the torn scans apart (counted: see the next test)."""
    summary = sc.summarize(fault_free, faults=False)
    assert summary["firmware"] == "v2"
    assert_fault_free_but_for(summary, fault_free, OPEN_DEFECTS, sessions=SESSIONS, min_pulses=5000)


def test_fault_free_v2_campaign_triggers_no_firmware_defect(fault_free: list[sc.SessionResult]) -> None:
    """No torn pattern either: every pattern that may differ from the one in force is copied under the
    mode-2 cover, so a scan that pre-empts the copy runs without current (counted as a dropout)."""
    summary = sc.summarize(fault_free, faults=False)
    failed = [r.index for r in fault_free if not r.ok]
    assert_fault_free(summary, failed, sessions=SESSIONS, min_pulses=5000)


def test_fault_free_v2_campaign_covers_what_it_claims(fault_free: list[sc.SessionResult]) -> None:
    summary = sc.summarize(fault_free, faults=False)
    for call in (*CAMPAIGN_CALLS, "measure"):
        assert summary["calls"].get(call, 0) >= 10, call
    assert summary["links"]["usb"] > 30 and summary["links"]["uart"] > 30
    assert 30 < summary["robust_encoding"] < SESSIONS - 30
    assert summary["electrodes_min_max"] == [1, 255]
    assert summary["biphasic"] > 30 and summary["regional_limits"] > 10 and summary["participant_cap"] > 10
    # the per-electrode limits were met by clipping, not only by refusals: regional sessions stimulated
    assert sum(r.pulses for r in fault_free if r.regions) > 500


def test_v2_fault_campaign_reports_every_loss_and_bounds_every_wrong_delivery() -> None:
    results = sc.run_campaign(FAULT_SESSIONS, seed=0, faults=True, firmware="v2")
    summary = sc.summarize(results, faults=True)
    assert summary["firmware"] == "v2"
    assert summary["faults_injected"] >= FAULT_SESSIONS
    assert summary["bytes_lost"] > 0
    assert summary["bytes_lost_unreported"] == 0
    assert summary["unexplained_wrong_deliveries"] == 0
    assert summary["faults_survived"] == summary["faults_injected"]
    assert summary["longest_wrong_delivery_s"] <= summary["recovery_bound_s"]
    assert summary["recovery_bound_s"] > COMMAND_TIMEOUT_S  # v2's recovery waits out the 2 s timeout


def test_the_v2_judge_holds_each_electrode_to_its_own_regional_limit() -> None:
    """A height that the session's largest request allows but the electrode's region does not."""
    seed = next(
        i for i in range(200) if sc.Session(i, i, False, "v2").regions
    )  # a 32-electrode session guarded by regions
    s = sc.Session(seed, seed, False, "v2")
    s.run()
    limits = s.electrode_limits_ua()
    assert limits[0] < max(limits[:32])  # electrode 0's region is the lowest
    over = int(limits[0]) + 100
    s.res.allowed_stim_ua = max(s.res.allowed_stim_ua, over)
    s.port.is_open = True
    code = over // 10
    s.port.write(c2.encode_electrode_num(1) + c2.encode_stim_mode(0) + c2.encode_pattern([code]))
    s.port.advance(0.05)
    res = s.judge()
    assert res.over_limit > 0 and not res.ok


# --- v2's recovery bound ------------------------------------------------------------------------------------


def test_the_v2_resync_bound_includes_the_2s_command_timeout() -> None:
    dev, port, board = _timed_v2()
    assert dev.resync_bound_s() > COMMAND_TIMEOUT_S  # before a configuration too
    dev.configure(StimConfig(electrode_count=32, current_ua=800))
    bound = dev.resync_bound_s()
    assert bound > COMMAND_TIMEOUT_S
    fs = FailSafe(dev, probe_interval_s=0.02, thread=False, signals=False, at_exit=False)
    assert fs.recovery_bound_s() > bound  # the fail-safe's default is the device's own bound
    assert fs.recovery_bound_s(resync_s=0.035) < 1.0  # an explicit figure still counts
    dev.close()


def test_a_failing_v2_resync_reaches_the_reset_line_within_its_bound() -> None:
    """The board stops answering (hung): the resync sends the probe, waits out the 2 s timeout, probes
    again, and pulls the reset line — within :meth:`Device.resync_bound_s`."""
    dev, port, board = _timed_v2()
    dev.configure(StimConfig(electrode_count=32, current_ua=800))
    dev.send_pattern([1] * 32)
    bound = dev.resync_bound_s()
    board.drop_replies = 10**6
    resets: list[float] = []
    real_reset = board.reset

    def reset(why: str = "reset") -> None:
        resets.append(port.now_s)
        board.drop_replies = 0
        real_reset(why)

    board.reset = reset  # type: ignore[method-assign]
    t0 = port.now_s
    try:
        dev.resync()
    except TactDeformError:
        pass
    assert resets, "the reset line was never pulled"
    assert COMMAND_TIMEOUT_S < resets[0] - t0 <= bound
    assert dev.resync_bound_s() >= bound
    port.advance(0.02)
    if dev.link_state is LinkState.IN_STEP:
        dev.close()


def test_close_is_proved_by_count_0_when_its_all_off_write_is_corrupted() -> None:
    """A UART corrupts the first byte of ``close``'s all-off write (the cover's mode command, read as an
    unknown byte, so what follows is read from a boundary elsewhere than the driver planned).  A sync
    reply to the count in force would prove only that the bytes were read; ``close`` on v2 ends at
    electrode count 0 and needs the sync reply 00, so nothing is scanned any more whatever the buffer
    holds."""
    from tactdeform_hw.device.driver.serial_driver import EtactileKitDevice
    from tactdeform_hw.emulator.faults import Fault, TimedPort
    from tactdeform_hw.emulator.timed.model_v2 import TimedEmulatorV2

    def session(faults: list[Fault]) -> tuple[float, TimedPort, TimedEmulatorV2]:
        board = TimedEmulatorV2("compact", 1, link="uart")
        port = TimedPort(board, link="uart", robust_encoding=False, faults=faults, seed=3)
        dev = EtactileKitDevice(port, firmware="v2")
        dev.configure(StimConfig(electrode_count=8, current_ua=300, pulse_width_us=200))
        dev.send_pattern([1] * 8)
        port.advance(0.05)
        t_close = port.now_s
        dev.close()
        return t_close, port, board

    t_close, _, _ = session([])  # where close's first byte goes, in the same simulated session
    _, port, board = session([Fault("corrupt", at_s=t_close - 1e-6)])
    hit = port.all_injected
    assert [f.kind.value for f in hit] == ["corrupt"] and hit[0].detail["before"] == "fb", hit
    assert board.state().electrode_num == 0  # nothing is scanned
    port.advance(0.05)
    assert board.peak_current_ua(since_us=(port.now_s - 0.04) * 1e6) == {}


def test_close_on_v2_leaves_the_electrode_count_at_0() -> None:
    dev, port, board = _timed_v2()
    dev.configure(StimConfig(electrode_count=8, current_ua=300, pulse_width_us=200))
    dev.send_pattern([1] * 8)
    dev.close()
    assert board.emulator.state().electrode_num == 0


def test_a_hung_255_electrode_board_is_reset_within_the_recovery_bound() -> None:
    """Campaign seed 8, fault session 1691: 255 electrodes at 7 Hz on a UART, the board's main loop hangs
    while the owner writes frames back to back.  The probe now runs before the owner's next frame (a busy
    owner cannot starve it), and the bound counts the probe's own wait behind a full queue
    (:meth:`Device.probe_bound_s`): the wrong deliveries end within it."""
    res = sc.run_session(1691, seed=8, faults=True, firmware="v2")
    assert "stop_reading" in res.faults and res.electrodes == 255
    assert res.ok, res.first_violation
    assert res.unexplained == 0 and 0 < res.wrong_after_fault_s <= res.recovery_bound_s
