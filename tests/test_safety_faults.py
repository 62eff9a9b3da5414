"""Fault injection: the whole pipeline through every fault, checked on the emulated scans.

For each fault the session (renderer-shaped frames → driver with a participant's guard → fail-safe with
probe, readback and refresh → faulty link → timed emulator) must:

* notice it (an error raised to the caller or a recovery by the fail-safe) — or, for a silent byte fault
  that the loss-tolerant encoding absorbed, show no lasting effect;
* never let a scan deliver current above an electrode's limit, or to an electrode meant off, for longer
  than the documented recovery time after the fault (:meth:`FailSafe.recovery_bound_s` plus the frame's
  own settle time) — and on the USB link, never above the participant's cap at all;
* lose no byte without the driver being told or noticing it.

Silent byte faults (drop, corrupt, duplicate, delay) run on the UART link model: on USB full speed the
bus's CRC, retries and data toggles turn them into reported transfer errors (``crc_error``).
"""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

from tactdeform_hw.device.driver.pacing import estimate_scan_us
from tactdeform_hw.emulator.faults import LINK_FAULTS, Fault, FaultKind, TimedPort, random_plan

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tools"))
import safety_scenarios as ss  # noqa: E402

SEEDS = (0, 1, 2)
REPORTED = {
    FaultKind.CUT,
    FaultKind.CRC_ERROR,
    FaultKind.RESET,
    FaultKind.STOP_READING,
    FaultKind.WATCHDOG_REBOOT,
}


def scenario(kind: FaultKind, seed: int) -> ss.Scenario:
    sc = ss.single_fault(kind, seed, at_s=0.3 + 0.061 * seed)
    if kind in LINK_FAULTS:
        sc.link = "uart"
    return sc


def check(res: ss.ScenarioResult, *, strict_cap: bool) -> None:
    assert res.injected, "the fault never struck"
    assert res.unexplained == [], res.unexplained[:5]
    assert res.unreported_losses == [], res.unreported_losses[:5]
    if strict_cap:
        assert res.max_current_ua <= res.limit_cap_ua
    assert res.final_state["pulse_height"] == 0  # closed: everything off at the end
    assert res.final_state["stim_pattern"][:32] == [0] * 32


@pytest.mark.parametrize("seed", SEEDS)
@pytest.mark.parametrize("kind", sorted(FaultKind, key=lambda k: k.value), ids=lambda k: k.value)
def test_each_fault_is_survived(kind: FaultKind, seed: int) -> None:
    res = ss.run(scenario(kind, seed))
    # drops fail low by construction (padding, no command-like payload, every copy twice); corruption
    # and duplication of a value byte on an unchecked link can set any height until noticed
    check(res, strict_cap=kind not in (FaultKind.CORRUPT, FaultKind.DUPLICATE))
    if kind in REPORTED:
        assert all(res.noticed), (res.injected, res.events)
    else:
        for noticed, effect in zip(res.noticed, res.effect):
            assert noticed or not effect or res.longest_after_fault_s <= res.recovery_bound_s


def test_faults_are_noticed_not_just_absorbed() -> None:
    """Across seeds, silent faults with a visible trace are noticed by the readback probe."""
    noticed = 0
    for seed in range(6):
        for kind in (FaultKind.DROP, FaultKind.CORRUPT, FaultKind.DUPLICATE):
            res = ss.run(scenario(kind, seed))
            noticed += sum(res.noticed)
    assert noticed >= 3


def test_a_stalled_owner_is_switched_off_within_watchdog_plus_one_scan() -> None:
    res = ss.run(ss.Scenario(owner_stops_at_s=0.45))  # ring 2 held: every outer electrode on
    assert res.owner_stop_on_s is not None
    assert 0.05 < res.owner_stop_on_s <= res.scenario.watchdog_s + 1 / 125
    assert any(e["kind"] == "watchdog" for e in res.events)


def test_many_mixed_faults_in_one_session() -> None:
    plan = random_plan(11, [k for k in FaultKind if k not in LINK_FAULTS] + [FaultKind.DELAY], 10, 0.1, 2.3)
    res = ss.run(ss.Scenario(faults=plan, seed=11, duration_s=2.4))
    check(res, strict_cap=True)
    assert sum(res.noticed) >= sum(1 for f in res.injected if f["kind"] != "delay")


def test_without_recovery_a_locked_parser_stimulates_on() -> None:
    """The control: without probing, a hung parser keeps the old frame on — the checks above can fail."""
    sc = ss.single_fault(FaultKind.STOP_READING, 0, at_s=0.35)
    sc.probe_s = None
    sc.refresh_s = None
    sc.watchdog_s = None  # type: ignore[assignment]
    res = ss.run(sc)
    assert res.longest_after_fault_s > 0.5, "a hung parser without recovery should have gone on stimulating"
    assert res.unreported_losses and not any(res.noticed)


def test_scan_estimate_matches_the_timed_emulator() -> None:
    from tactdeform_hw.emulator.firmware.scan import ScanConfig, scan_duration_ns

    for levels, width, discharge in [
        ([1] * 32, 200, 45),
        ([1] * 32, 200, 50),
        ([1, 0, 2, 0] * 8, 100, 20),
        ([0] * 32, 200, 45),
    ]:
        cfg = ScanConfig(
            electrode_num=len(levels),
            pulse_width=width,
            discharge_time=discharge,
            hv513_num=4,
            pattern=bytes(levels),
            pulse_height=100,
        )
        exact = scan_duration_ns(cfg) / 1000
        est = estimate_scan_us(levels, width, discharge)
        assert exact <= est <= exact * 1.01 + 5, (levels[:4], exact, est)


def test_fault_plan_is_seeded_and_validated() -> None:
    assert random_plan(3, ["drop", "reset"], 5, 0, 1) == random_plan(3, ["drop", "reset"], 5, 0, 1)
    with pytest.raises(Exception, match="count"):
        Fault(FaultKind.DROP, 0.1, count=0)
    port = TimedPort(faults=[Fault("drop", 0.0)], seed=5)
    assert port.faulty_link.pending and port.robust_encoding


def test_renderer_pipeline_through_a_fault() -> None:
    """The real renderer (scene, trajectory, pattern manager) on the faulty timed emulator."""
    from tactdeform_hw.device import EtactileKitDevice, StimConfig
    from tactdeform_hw.device.safety.failsafe import FailSafe
    from tactdeform_hw.device.safety.guard import SafetyGuard
    from tactdeform_hw.emulator.faults import Intent, check_deliveries
    from tactdeform_hw.render import pipeline as render
    from tactdeform_hw.render.array import ElectrodeArray
    from tactdeform_hw.render.scene import load_scene
    from tactdeform_hw.render.trajectories import make_trajectory

    prof = ss.PROFILE
    scene = load_scene("cube")
    poses = make_trajectory("approach-face", scene, rate_hz=ss.RENDERER_MAX_RATE_HZ)
    scene.prepare()
    array = ElectrodeArray.tactdeform()
    mapping = array.channel_mapping()
    t_fault = poses[len(poses) // 2].t_s
    port = TimedPort(
        link="usb", faults=[Fault(FaultKind.STOP_READING, t_fault), Fault(FaultKind.CRC_ERROR, t_fault + 0.2)]
    )
    dev = EtactileKitDevice(port, guard=SafetyGuard.from_profile(prof, region_of=None), mapping=mapping)
    fs = FailSafe(
        dev,
        probe_interval_s=0.02,
        refresh_interval_s=0.05,
        verify_readback=True,
        thread=False,
        signals=False,
        at_exit=False,
    ).start()
    port.hooks.append(lambda t: fs.poll(t))
    renderer = render.Renderer(
        scene,
        dev,
        array=array,
        current_ua=prof.stimulation_ua,
        stim_config=StimConfig(electrode_count=mapping.hw_channels, current_ua=prof.stimulation_ua),
    )
    intents = [Intent(0.0, (0,) * 32)]
    errors = 0
    t0 = 0.05
    for pose in poses:
        port.advance_to(t0 + pose.t_s)
        t_step = port.now_s
        try:
            recs = renderer.step(pose)
        except Exception:  # noqa: BLE001 - the renderer's loop reports and goes on
            errors += 1
            continue
        sent = [r for r in recs if r.sent]
        for r in sent:
            intents.append(Intent(t_step, tuple(1 if v else 0 for v in r.electrodes)))
        if not sent:
            dev.keepalive()
    port.advance(0.2)
    fs.stop()
    limits = SafetyGuard.from_profile(prof).electrode_limits(32)
    hw_to_app = {hw: app for app, hw in enumerate(mapping.app_to_hw)}
    chk = check_deliveries(port.emulator, intents, limits, hw_to_app)
    bound = fs.recovery_bound_s() + 0.012
    times = [f.t_s for f in port.all_injected]
    assert len(times) == 2 and renderer.summary.frames_sent > 3
    for v in chk.violations:
        assert any(0 <= v["t_s"] - t <= bound for t in times), v
    assert chk.max_current_ua <= prof.cap_ua
    assert fs.recoveries >= 1
    dev.close()
