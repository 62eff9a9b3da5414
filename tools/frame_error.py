"""Frame-index error of eq. 3 against run time, per tracking rate and per way of integrating travel.

Eq. 3 sets the expansion frame to n(t) = ⌊α ∫ v_approach dt / d⌋.  A tracker never delivers v; it
delivers positions at 30–120 Hz, with timestamp jitter, noise and the odd dropped sample.  This tool
simulates such a stream over a finger pressing in and out along a surface normal (speeds up to about
150 mm/s, depths to 20 mm) for up to an eight-hour session, computes n at every sample with each
method below, and compares the frame the pad would show at every millisecond with the ground truth
evaluated on a 1 kHz grid from the exact motion:

* ``displacement`` — what the renderer does: the displacement between successive samples, projected on
  the normal, added to a whole-frame + compensated-remainder accumulator
  (:class:`tactdeform_hw.render.contexts.FrameAccumulator`).  The sum telescopes to the net
  displacement, so the error stays at the sampling latency however long the run.
* ``displacement-f32`` — the same sum in single precision, as an engine script with float positions
  would keep it.
* ``velocity-rect`` — differentiate (Δx / Δt of the reported timestamps), then integrate with the
  render loop's nominal frame time (rectangle rule): dropped samples and timestamp noise add up.
* ``velocity-trapezoid`` — differentiate, then integrate with the trapezoid rule over reported Δt.
* ``velocity-ema`` — differentiate, smooth (exponential, τ = 50 ms) as trackers' velocity outputs are,
  integrate over reported Δt.
* ``fixed-interval`` — the pilots' rejected scheme: a new frame every d / v_nominal seconds (20 mm/s)
  while the finger moves toward the surface, whatever its speed.

Usage::

    python tools/frame_error.py                       # 8 h, rates 30/72/90/120 Hz, table + frame_error.png
    python tools/frame_error.py --duration 600 --png out.png --json

The PNG needs matplotlib (``pip install 'tactdeform_hw[plot]'``); ``--no-plot`` skips it.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from tactdeform_hw.errors import MissingDependencyError  # noqa: E402
from tactdeform_hw.render.contexts import ALPHA, D_ELECTRODE_MM, FrameAccumulator  # noqa: E402

METHODS: tuple[str, ...] = (
    "displacement",
    "displacement-f32",
    "velocity-rect",
    "velocity-trapezoid",
    "velocity-ema",
    "fixed-interval",
)
RATES_HZ: tuple[float, ...] = (30.0, 72.0, 90.0, 120.0)
BIN_EDGES_S: tuple[float, ...] = (0.0, 10.0, 60.0, 600.0, 3600.0, 8 * 3600.0)
GT_RATE_HZ = 1000.0

# Tracker model: sampling jitter, timestamp noise, position noise, drop probability.
SAMPLE_JITTER_S = 0.0005
STAMP_NOISE_S = 0.0005
POSITION_NOISE_MM = 0.05
DROP_PROBABILITY = 0.01
EMA_TAU_S = 0.05
NOMINAL_SPEED_MM_S = 20.0


def travel_mm(t: np.ndarray) -> np.ndarray:
    """Net travel toward the surface (mm): press-and-release cycles of several speeds and depths."""
    return (
        6.0 * (1.0 - np.cos(2 * np.pi * 0.35 * t))
        + 2.5 * np.sin(2 * np.pi * 1.7 * t + 0.4)
        + 4.0 * (1.0 - np.cos(2 * np.pi * 0.05 * t))
        + 1.5 * np.sin(2 * np.pi * 3.1 * t + 1.3)
    )


def simulate_stream(duration_s: float, rate_hz: float, rng: np.random.Generator) -> dict[str, np.ndarray]:
    n = int(duration_s * rate_hz) + 1
    k = np.arange(n)
    t_true = k / rate_hz + rng.normal(0.0, SAMPLE_JITTER_S, n)
    t_true[0] = 0.0
    t_true = np.maximum.accumulate(t_true)
    keep = rng.random(n) >= DROP_PROBABILITY
    keep[0] = True
    t_true = t_true[keep]
    t_rep = t_true + rng.normal(0.0, STAMP_NOISE_S, t_true.size)
    t_rep[0] = t_true[0]
    t_rep = np.maximum.accumulate(t_rep)
    x = travel_mm(t_true) + rng.normal(0.0, POSITION_NOISE_MM, t_true.size)
    return {"t_true": t_true, "t_rep": t_rep, "x": x}


def integrate(method: str, s: dict[str, np.ndarray], rate_hz: float) -> np.ndarray:
    """Travel (mm) at each received sample, starting at 0."""
    x, t = s["x"], s["t_rep"]
    dx = np.diff(x)
    dt = np.diff(t)
    safe_dt = np.where(dt > 1e-6, dt, 1e-6)
    v = dx / safe_dt
    out = np.empty_like(x)
    out[0] = 0.0
    if method == "displacement":
        acc = FrameAccumulator(D_ELECTRODE_MM / ALPHA)
        add = acc.add
        unit = acc.unit_mm
        res = out[1:]
        for i, d in enumerate(dx.tolist()):
            add(d)
            res[i] = acc.whole * unit + acc.rem
        return out
    if method == "displacement-f32":
        out[1:] = np.cumsum(dx.astype(np.float32), dtype=np.float32)
        return out
    if method == "velocity-rect":
        out[1:] = np.cumsum(v / rate_hz)
        return out
    if method == "velocity-trapezoid":
        vv = np.concatenate(([0.0], v))
        out[1:] = np.cumsum(0.5 * (vv[:-1] + vv[1:]) * dt)
        return out
    if method == "velocity-ema":
        a = 1.0 - np.exp(-dt / EMA_TAU_S)
        vs = np.empty_like(v)
        acc_v = 0.0
        for i, (ai, vi) in enumerate(zip(a.tolist(), v.tolist())):
            acc_v += ai * (vi - acc_v)
            vs[i] = acc_v
        out[1:] = np.cumsum(vs * dt)
        return out
    if method == "fixed-interval":
        # Frames tick at the nominal interval while moving toward (+1) or away (-1) from the surface.
        direction = np.sign(dx)
        out[1:] = np.cumsum(direction * NOMINAL_SPEED_MM_S * dt)
        return out
    raise ValueError(method)


def frame_errors(
    duration_s: float,
    rate_hz: float,
    seed: int,
    methods: tuple[str, ...],
    progress: Callable[[str], None] | None = None,
) -> dict[str, dict[str, list[float]]]:
    """Per method: mean |error|, max |error| and fraction of time wrong, per run-time bin."""
    rng = np.random.default_rng(seed)
    s = simulate_stream(duration_s, rate_hz, rng)
    frames = {}
    for m in methods:
        t0 = time.perf_counter()
        trav = integrate(m, s, rate_hz)
        frames[m] = np.floor(ALPHA * trav / D_ELECTRODE_MM + 1e-12).astype(np.int64)
        if progress:
            progress(f"  {rate_hz:g} Hz {m}: {time.perf_counter() - t0:.1f} s")
    edges = [e for e in BIN_EDGES_S if e < duration_s] + [duration_s]
    nb = len(edges) - 1
    sums = {m: np.zeros(nb) for m in methods}
    maxs = {m: np.zeros(nb) for m in methods}
    wrong = {m: np.zeros(nb) for m in methods}
    counts = np.zeros(nb)
    x0 = float(travel_mm(np.array([0.0]))[0])
    chunk = 600.0
    start = 0.0
    t_true = s["t_true"]
    while start < duration_s:
        stop = min(duration_s, start + chunk)
        tau = np.arange(math.ceil(start * GT_RATE_HZ), math.ceil(stop * GT_RATE_HZ)) / GT_RATE_HZ
        truth = np.floor(ALPHA * (travel_mm(tau) - x0) / D_ELECTRODE_MM + 1e-12).astype(np.int64)
        j = np.searchsorted(t_true, tau, side="right") - 1
        b = np.searchsorted(edges, tau, side="right") - 1
        b = np.clip(b, 0, nb - 1)
        counts += np.bincount(b, minlength=nb)
        for m in methods:
            e = np.abs(frames[m][j] - truth).astype(float)
            sums[m] += np.bincount(b, weights=e, minlength=nb)
            wrong[m] += np.bincount(b, weights=(e > 0).astype(float), minlength=nb)
            for i in np.unique(b):
                maxs[m][i] = max(maxs[m][i], float(e[b == i].max()))
        start = stop
    safe = np.maximum(counts, 1)
    return {
        m: {
            "bin_end_s": edges[1:],
            "mean_abs": (sums[m] / safe).tolist(),
            "max_abs": maxs[m].tolist(),
            "fraction_wrong": (wrong[m] / safe).tolist(),
        }
        for m in methods
    }


def _label(seconds: float) -> str:
    if seconds >= 3600:
        return f"{seconds / 3600:g} h"
    if seconds >= 60:
        return f"{seconds / 60:g} min"
    return f"{seconds:g} s"


def table(results: dict[float, dict[str, dict[str, list[float]]]]) -> str:
    lines = []
    for rate, per in results.items():
        ends = next(iter(per.values()))["bin_end_s"]
        header = "| method | " + " | ".join(f"≤ {_label(e)}" for e in ends) + " |"
        lines.append(f"\n**{rate:g} Hz** — mean |frame error| (max) over each run-time interval\n")
        lines.append(header)
        lines.append("|" + "---|" * (len(ends) + 1))
        for m, r in per.items():
            cells = [f"{a:.3f} ({int(b)})" for a, b in zip(r["mean_abs"], r["max_abs"])]
            lines.append(f"| {m} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def plot(results: dict[float, dict[str, dict[str, list[float]]]], path: Path) -> None:
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError as exc:  # pragma: no cover - depends on the environment
        raise MissingDependencyError("matplotlib", "plot", "the frame-error plot") from exc
    rates = list(results)
    fig, axes = plt.subplots(1, len(rates), figsize=(4.2 * len(rates), 3.8), sharey=True, squeeze=False)
    for ax, rate in zip(axes[0], rates):
        for m, r in results[rate].items():
            style = "--" if m.endswith("f32") else "-"
            ax.plot(r["bin_end_s"], np.maximum(r["mean_abs"], 1e-4), style, marker="o", label=m)
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_title(f"{rate:g} Hz tracking")
        ax.set_xlabel("run time (s)")
        ax.grid(True, which="both", alpha=0.3)
    axes[0][0].set_ylabel("mean |frame index error| (frames)")
    axes[0][-1].legend(fontsize=7, loc="upper left")
    fig.suptitle("Eq. 3 frame index against a 1 kHz ground truth")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument(
        "--duration", type=float, default=8 * 3600.0, help="simulated run time in s (default 8 h)"
    )
    ap.add_argument("--rates", default=",".join(f"{r:g}" for r in RATES_HZ), help="tracking rates in Hz")
    ap.add_argument("--methods", default=",".join(METHODS), help="integration methods to compare")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--png", default="frame_error.png", help="plot file (default frame_error.png)")
    ap.add_argument("--no-plot", action="store_true")
    ap.add_argument("--json", action="store_true", help="print the results as JSON instead of a table")
    args = ap.parse_args(argv)
    if not (math.isfinite(args.duration) and args.duration > 0):
        ap.error("--duration must be > 0")
    rates = [float(r) for r in args.rates.split(",")]
    methods = tuple(m.strip() for m in args.methods.split(","))
    for m in methods:
        if m not in METHODS:
            ap.error(f"unknown method {m!r} (known: {', '.join(METHODS)})")
    results: dict[float, dict[str, dict[str, list[float]]]] = {}

    def progress(msg: str) -> None:
        print(msg, file=sys.stderr, flush=True)

    for r in rates:
        progress(f"{r:g} Hz: {int(args.duration * r)} samples")
        results[r] = frame_errors(args.duration, r, args.seed, methods, progress)
    if args.json:
        print(json.dumps({f"{r:g}": v for r, v in results.items()}, indent=1))
    else:
        print(table(results))
    if not args.no_plot:
        plot(results, Path(args.png))
        progress(f"wrote {args.png}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
