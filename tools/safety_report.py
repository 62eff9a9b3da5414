"""The safety figures of the README: faults injected and survived, fuzz cases run, the longest a channel
stayed on after its owner stopped, and bytes lost without being reported.

    python tools/safety_report.py            # the README figures (about a minute)
    python tools/safety_report.py --quick    # fewer seeds
    python tools/safety_report.py --json     # one JSON object

Everything runs in simulated time on the timed emulator (see ``tools/safety_scenarios.py``) and is
deterministic for the given seeds.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from typing import Any

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
sys.path.insert(0, str(HERE.parent))

import safety_scenarios as ss  # noqa: E402

from tactdeform_hw.emulator.faults import LINK_FAULTS, FaultKind, random_plan  # noqa: E402


def fault_sweep(seeds: int) -> dict[str, Any]:
    per_kind: dict[str, dict[str, Any]] = {}
    results = []
    for kind in FaultKind:
        row = {
            "injected": 0,
            "survived": 0,
            "noticed": 0,
            "no_effect": 0,
            "repaired_silently": 0,
            "longest_effect_s": 0.0,
            "above_cap": 0,
            "max_current_ua": 0.0,
        }
        for seed in range(seeds):
            sc = ss.single_fault(kind, seed, at_s=0.25 + 0.6 * seed / max(1, seeds))
            if kind in LINK_FAULTS:
                sc.link = "uart"
            res = ss.run(sc)
            results.append(res)
            _tally(row, res)
        per_kind[kind.value] = row
    mixed = []
    for seed in range(max(2, seeds // 3)):
        usb_kinds = [k for k in FaultKind if k not in LINK_FAULTS] + [FaultKind.DELAY]
        for link, kinds in (("usb", usb_kinds), ("uart", list(FaultKind))):
            plan = random_plan(100 + seed, kinds, 8, 0.1, 2.2)
            res = ss.run(ss.Scenario(faults=plan, seed=100 + seed, link=link, duration_s=2.4))
            results.append(res)
            row = {
                "injected": 0,
                "survived": 0,
                "noticed": 0,
                "no_effect": 0,
                "repaired_silently": 0,
                "longest_effect_s": 0.0,
                "above_cap": 0,
                "max_current_ua": 0.0,
            }
            _tally(row, res)
            mixed.append({"link": link, "seed": 100 + seed, **row})
    return {"per_kind": per_kind, "mixed": mixed, "results": results}


def _tally(row: dict[str, Any], res: ss.ScenarioResult) -> None:
    n = len(res.injected)
    row["injected"] += n
    ok = not res.unexplained and not res.unreported_losses
    row["survived"] += n if ok else 0
    row["noticed"] += sum(res.noticed)
    row["no_effect"] += sum(1 for e in res.effect if not e)
    row["repaired_silently"] += sum(1 for nt, e in zip(res.noticed, res.effect) if e and not nt)
    row["longest_effect_s"] = max(row["longest_effect_s"], res.longest_after_fault_s)
    if res.max_current_ua > res.limit_cap_ua:
        row["above_cap"] += 1
    row["max_current_ua"] = max(row["max_current_ua"], res.max_current_ua)


def owner_stops(count: int) -> dict[str, Any]:
    worst = 0.0
    runs = []
    for k in range(count):
        stop = 0.1 + 0.6 * k / max(1, count)  # across the frame cycle: approach, hold, slide, idle
        res = ss.run(ss.Scenario(owner_stops_at_s=stop))
        on = res.owner_stop_on_s or 0.0
        worst = max(worst, on)
        runs.append(round(on, 4))
    limit = 0.1 + 1 / 125
    return {
        "runs": count,
        "longest_on_after_stop_s": round(worst, 4),
        "limit_s": limit,
        "within": worst <= limit,
        "per_run_s": runs,
    }


def pacing_check() -> dict[str, Any]:
    """A loss-free session at the renderer's highest rate, every frame different, plus reconfigurations."""
    from tactdeform_hw.device import EtactileKitDevice, StimConfig
    from tactdeform_hw.device.safety.guard import TACTDEFORM_REGION_OF, SafetyGuard
    from tactdeform_hw.emulator.faults import TimedPort

    out = {}
    for link in ("usb", "uart"):
        for robust in (False, True):
            port = TimedPort(link=link, robust_encoding=robust)
            dev = EtactileKitDevice(port, guard=SafetyGuard.from_profile(ss.PROFILE))
            dev.configure(StimConfig(current_ua=1500))
            n = int(ss.RENDERER_MAX_RATE_HZ * 2)
            for i in range(n):
                port.advance_to(0.05 + i / ss.RENDERER_MAX_RATE_HZ)
                region = (4, 0, 3, 8, 1)[i % 5]
                dev.send_pattern([1 if r == region else 0 for r in TACTDEFORM_REGION_OF])
            for i in range(4):
                dev.configure(StimConfig(current_ua=500 + 100 * i, rate_hz=125 - i))
                dev.resync()
            dev.close()
            port.emulator.run_until_idle()
            out[f"{link}{'+robust' if robust else ''}"] = {
                "frames": n,
                "bytes_lost": sum(lo.count for lo in port.emulator.losses),
                "commands_out_of_step": sum(1 for c in port.emulator.commands if not c.in_sync),
                "queue_high_water": port.emulator.queue.high_water,
            }
    return out


def fuzz_cases() -> dict[str, Any]:
    sys.path.insert(0, str(HERE.parent))  # the repository root: ``tests`` is a package
    from tests import test_safety_fuzz as fz

    fz.CASES.clear()
    for name in dir(fz):
        if name.startswith("test_"):
            getattr(fz, name)()
    return {"total": sum(fz.CASES.values()), "per_property": dict(fz.CASES)}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=12, help="seeds per fault kind (default 12)")
    ap.add_argument("--quick", action="store_true", help="3 seeds per fault kind")
    ap.add_argument("--no-fuzz", action="store_true", help="skip the fuzz count")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args(argv)
    seeds = 3 if args.quick else args.seeds
    t0 = time.perf_counter()
    sweep = fault_sweep(seeds)
    results = sweep.pop("results")
    stops = owner_stops(6 if args.quick else 24)
    pacing = pacing_check()
    fuzz = {"total": None} if args.no_fuzz else fuzz_cases()
    injected = sum(len(r.injected) for r in results)
    survived = sum(len(r.injected) for r in results if not r.unexplained and not r.unreported_losses)
    unreported = sum(lo["count"] for r in results for lo in r.unreported_losses)
    lost = sum(lo["count"] for r in results for lo in r.losses)
    bounds = sorted({round(r.recovery_bound_s, 4) for r in results})
    report = {
        "faults_injected": injected,
        "faults_survived": survived,
        "faults_noticed": sum(sum(r.noticed) for r in results),
        "sessions": len(results),
        "recovery_bound_s": bounds,
        "longest_effect_after_fault_s": round(max(r.longest_after_fault_s for r in results), 4),
        "sessions_above_cap": [
            {
                "faults": [f["kind"] for f in r.injected],
                "max_current_ua": round(r.max_current_ua, 1),
                "longest_effect_s": round(r.longest_after_fault_s, 4),
            }
            for r in results
            if r.max_current_ua > r.limit_cap_ua
        ],
        "bytes_lost_in_fault_runs": lost,
        "bytes_lost_unreported": unreported + sum(v["bytes_lost"] for v in pacing.values()),
        "owner_stop": stops,
        "pacing": pacing,
        "fuzz_cases": fuzz["total"],
        "fuzz": fuzz,
        "per_kind": sweep["per_kind"],
        "mixed": sweep["mixed"],
        "wall_s": round(time.perf_counter() - t0, 1),
    }
    if args.json:
        json.dump(report, sys.stdout, indent=2, default=str)
        print()
        return 0
    print(
        f"faults injected {injected}, survived {survived} (noticed {report['faults_noticed']}) in "
        f"{len(results)} sessions"
    )
    print(
        f"  recovery bound {bounds} s; longest wrong delivery after a fault "
        f"{report['longest_effect_after_fault_s']} s"
    )
    print(
        f"  {'kind':16} {'inj':>4} {'surv':>4} {'noticed':>7} {'no eff.':>7} {'repaired':>8} "
        f"{'longest s':>9} {'>cap':>4}"
    )
    for k, row in report["per_kind"].items():
        print(
            f"  {k:16} {row['injected']:4d} {row['survived']:4d} {row['noticed']:7d} {row['no_effect']:7d} "
            f"{row['repaired_silently']:8d} {row['longest_effect_s']:9.4f} {row['above_cap']:4d}"
        )
    for m in report["mixed"]:
        print(
            f"  mixed {m['link']:4} seed {m['seed']}: {m['injected']} faults, {m['survived']} survived, "
            f"{m['noticed']} noticed"
        )
    if report["sessions_above_cap"]:
        print(
            "  above the participant's cap (silent corruption/duplication on a UART, bounded): "
            f"{report['sessions_above_cap']}"
        )
    print(
        f"longest a channel stayed on after its owner stopped: {stops['longest_on_after_stop_s']} s "
        f"(limit: watchdog 0.1 s + one scan period = {stops['limit_s']:.4g} s) over {stops['runs']} runs"
    )
    print(
        f"bytes lost without being reported: {report['bytes_lost_unreported']} "
        f"(lost in fault runs, all reported: {lost}); pacing: {json.dumps(pacing)}"
    )
    print(f"fuzz cases run: {fuzz['total']} {fuzz.get('per_property', '')}")
    print(f"({report['wall_s']} s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
