"""Timing error of the fast engines against the event-exact one, and what each costs to run.

Three fidelities run the same host scenarios (writes at given times over USB or UART):

* ``event-exact`` — :class:`tactdeform_hw.emulator.timed.model_v1_2.TimedEmulator`: every byte, parser call,
scan
  and watchdog; the reference (error 0 by definition);
* ``analytic`` — :func:`tactdeform_hw.emulator.timed.analytic.run_analytic`: closed-form scans and a command
  model without the receive queue, torn reads or the u16 spin;
* ``nominal`` — :func:`tactdeform_hw.emulator.timed.analytic.run_nominal`: "pulse width + discharge per
channel,
  commands effective on arrival", the arithmetic a paper does by hand.

For every scenario and simulated duration it reports the wall time, the speed (device time / wall time)
and the errors against the event-exact run: scan alarm times, command effect times and the first pulse
of each channel after each pattern (max and mean, µs), and how many commands one engine never applied
while the other did (``unmatched``).  The PNG shows max error against wall run time (one point per
scenario and duration) and against simulated duration (drift).

Usage::

    python tools/timing_error.py                          # 1 s and 10 s runs, table + timing_error.png
    python tools/timing_error.py --durations 1 10 60 --png out.png --json

The PNG needs matplotlib (``pip install 'tactdeform_hw[plot]'``); ``--no-plot`` skips it.
"""

from __future__ import annotations

import argparse
import json
import random
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

from tactdeform_hw.emulator.firmware.scan import ScanConfig  # noqa: E402
from tactdeform_hw.emulator.timed.analytic import Scenario, run_analytic, run_event_exact, run_nominal  # noqa: E402
from tactdeform_hw.emulator.timed.model_v1_2 import configuration_bytes  # noqa: E402
from tactdeform_hw.errors import MissingDependencyError  # noqa: E402
from tactdeform_hw.protocol import encode_pattern  # noqa: E402


def _updates(
    name: str,
    link: str,
    duration_s: float,
    *,
    n: int = 32,
    rate: int = 125,
    width: int = 200,
    discharge: int = 45,
    update_hz: float = 0.0,
    values: tuple[int, ...] = (0, 1),
    burst: int = 1,
    seed: int = 1,
) -> Scenario:
    cfg = ScanConfig.make(n, 1, pulse_width_us=width, discharge_us=discharge, rate_hz=rate)
    writes: list[tuple[float, bytes]] = [(0.0, configuration_bytes(cfg, rate))]
    rng = random.Random(seed)
    if update_hz:
        t = 20_000.0
        while t < duration_s * 1e6:
            data = b"".join(encode_pattern([rng.choice(values) for _ in range(n)]) for _ in range(burst))
            writes.append((t, data))
            t += 1e6 / update_hz
    return Scenario(name, writes, duration_s * 1e6, link)


SCENARIOS: dict[str, Callable[[float], Scenario]] = {
    "steady-usb": lambda d: _updates("steady-usb", "usb", d),
    "render60-usb": lambda d: _updates("render60-usb", "usb", d, update_hz=60),
    "render60-uart": lambda d: _updates("render60-uart", "uart", d, update_hz=60),
    "8el-500hz-uart": lambda d: _updates(
        "8el-500hz-uart", "uart", d, n=8, rate=500, width=100, update_hz=100
    ),
    "burst10-usb": lambda d: _updates("burst10-usb", "usb", d, update_hz=2, burst=10),
    "overrun-d50-usb": lambda d: _updates("overrun-d50-usb", "usb", d, discharge=50, update_hz=60),
}


def measure(durations: list[float], names: list[str]) -> list[dict[str, Any]]:
    rows: list[dict[str, Any]] = []
    for name in names:
        for d in durations:
            sc = SCENARIOS[name](d)
            ref, emu = run_event_exact(sc)
            summary = emu.reports.summary()
            rows.append(
                {
                    "scenario": name,
                    "duration_s": d,
                    "engine": "event-exact",
                    "wall_s": ref.wall_s,
                    "speed": d / ref.wall_s if ref.wall_s else float("inf"),
                    "scan_start_max_us": 0.0,
                    "effect_max_us": 0.0,
                    "first_pulse_max_us": 0.0,
                    "unmatched": 0,
                    "scans": int(ref.scan_start_ns.size),
                    "bytes_lost": summary["bytes_lost"],
                    "torn_scans": summary["torn_scans"],
                    "overruns": summary["overruns"],
                }
            )
            for runner in (run_analytic, run_nominal):
                tl = runner(sc)
                err = tl.compare(ref)
                rows.append(
                    {
                        "scenario": name,
                        "duration_s": d,
                        "engine": tl.engine,
                        "wall_s": tl.wall_s,
                        "speed": d / tl.wall_s if tl.wall_s else float("inf"),
                        "scan_start_max_us": err["scan_start_max_us"],
                        "scan_start_mean_us": err["scan_start_mean_us"],
                        "effect_max_us": err["effect_max_us"],
                        "effect_mean_us": err["effect_mean_us"],
                        "first_pulse_max_us": err["first_pulse_max_us"],
                        "first_pulse_mean_us": err["first_pulse_mean_us"],
                        "unmatched": err["unmatched"],
                        "scans": err["scans"],
                        "notes": tl.notes,
                    }
                )
    return rows


def table(rows: list[dict[str, Any]]) -> str:
    head = (
        f"{'scenario':<17}{'dur s':>6} {'engine':<12}{'wall s':>9}{'x real':>10}"
        f"{'scan max':>11}{'effect max':>12}{'1st pulse max':>15}{'unmatched':>10}"
    )
    lines = [head, "-" * len(head)]
    for r in rows:
        lines.append(
            f"{r['scenario']:<17}{r['duration_s']:>6g} "
            f"{r['engine']:<12}{r['wall_s']:>9.4f}{r['speed']:>10.0f}{r['scan_start_max_us']:>11.1f}"
            f"{r['effect_max_us']:>12.1f}{r['first_pulse_max_us']:>15.1f}{r['unmatched']:>10d}"
        )
    lines.append("errors in us against the event-exact engine; 'x real' = simulated time / wall time")
    return "\n".join(lines)


def plot(rows: list[dict[str, Any]], path: Path) -> None:
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError as exc:
        raise MissingDependencyError("matplotlib", "plot", "the timing-error plot") from exc
    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(12, 4.8))
    colors = {"event-exact": "tab:blue", "analytic": "tab:green", "nominal": "tab:red"}
    for eng, col in colors.items():
        sel = [r for r in rows if r["engine"] == eng]
        err = [max(r["scan_start_max_us"], r["effect_max_us"], r["first_pulse_max_us"]) for r in sel]
        ax1.scatter([r["wall_s"] for r in sel], [max(e, 0.01) for e in err], c=col, label=eng, alpha=0.8)
        for scen in sorted({r["scenario"] for r in sel}):
            pts = sorted(
                (r["duration_s"], max(r["scan_start_max_us"], r["effect_max_us"], r["first_pulse_max_us"]))
                for r in sel
                if r["scenario"] == scen
            )
            ax2.plot([p[0] for p in pts], [max(p[1], 0.01) for p in pts], "o-", c=col, alpha=0.6)
    ax1.set_xscale("log")
    ax1.set_yscale("log")
    ax1.set_xlabel("wall run time (s)")
    ax1.set_ylabel("max timing error vs event-exact (us; 0 drawn at 0.01)")
    ax1.set_title("error against run time")
    ax1.legend()
    ax2.set_xscale("log")
    ax2.set_yscale("log")
    ax2.set_xlabel("simulated duration (s)")
    ax2.set_ylabel("max timing error (us)")
    ax2.set_title("error against simulated duration (per scenario)")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument(
        "--durations", type=float, nargs="+", default=[1.0, 10.0], help="simulated seconds per run"
    )
    ap.add_argument("--scenarios", nargs="+", default=list(SCENARIOS), choices=list(SCENARIOS))
    ap.add_argument(
        "--png", type=Path, default=Path("timing_error.png"), help="plot file (default timing_error.png)"
    )
    ap.add_argument("--no-plot", action="store_true")
    ap.add_argument("--json", action="store_true", help="print the rows as JSON instead of the table")
    args = ap.parse_args(argv)
    if any(not d > 0 for d in args.durations):
        ap.error("durations must be > 0")
    rows = measure(args.durations, args.scenarios)
    if args.json:
        json.dump(rows, sys.stdout, indent=2, default=str)
        sys.stdout.write("\n")
    else:
        print(table(rows))
    if not args.no_plot:
        plot(rows, args.png)
        print(f"wrote {args.png}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
