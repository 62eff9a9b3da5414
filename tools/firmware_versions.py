"""Firmware v1.2 and v2 side by side: golden vectors matched, the TactDeform setting's scan budget, and
host write → pattern in force for one frame of 32 per-electrode intensities.

    python tools/firmware_versions.py            # the table
    python tools/firmware_versions.py --json     # the same figures as JSON
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from tactdeform_hw.emulator import Emulator  # noqa: E402
from tactdeform_hw.emulator.firmware.firmware_scan import HOST_BUILD, FirmwareScanConfig, budget  # noqa: E402
from tactdeform_hw.emulator.firmware.scan import ScanConfig  # noqa: E402
from tactdeform_hw.emulator.records.reports import firmware_budget  # noqa: E402
from tactdeform_hw.emulator.timed.model_v1_2 import pattern_latency  # noqa: E402
from tactdeform_hw.emulator.timed.model_v2 import pattern_in_force_v2  # noqa: E402
from tactdeform_hw.emulator.timed.timing import DEFAULT_MODEL  # noqa: E402

GOLDEN = Path(__file__).resolve().parents[1] / "tests" / "data" / "protocol_vectors_v2.jsonl"


def vectors_matched() -> dict[str, int]:
    """v2 golden vectors reached exactly, driven by their recorded arrivals and final times."""
    total = matched = 0
    for line in GOLDEN.read_text().splitlines():
        v = json.loads(line)
        total += 1
        emu = Emulator(firmware="v2")
        arrivals = v.get("arrivals") or [[0, v["stream"]]]
        tx = b"".join(emu.feed(bytes.fromhex(h), at_us=int(t)) for t, h in arrivals)
        if v.get("final_time_us") is not None:
            tx += emu.advance(int(v["final_time_us"]))
        state = emu.state()
        regs = state.as_dict()
        ok = (
            tx.hex() == v["expect"]["tx"]
            and all(regs[k] == val for k, val in v["expect"].items() if k not in ("tx", "period_us"))
            and abs(state.period_us - v["expect"]["period_us"]) <= 1e-6 * max(1.0, v["expect"]["period_us"])
        )
        matched += ok
    return {"matched": matched, "total": total}


def budgets() -> dict[str, dict[str, float]]:
    """The TactDeform setting on each version, by its own scan engine, with the chip-select writes inside
    the exchange and costed apart."""
    v12 = ScanConfig.make(32, 1, pulse_width_us=200, pulse_height=100, discharge_us=45, rate_hz=125)
    v2 = FirmwareScanConfig(32, [100] * 32, 200, 45, frequency_hz=125)
    both = {
        "v1.2 cs inside": firmware_budget(v12, DEFAULT_MODEL),
        "v1.2 cs costed": firmware_budget(v12, DEFAULT_MODEL.with_(cs_writes_costed=True)),
        "v2 cs inside": budget(v2, "v2"),
        "v2 cs costed": budget(v2, "v2", HOST_BUILD),
    }
    return {
        name: {"scan_us": b.scan_us, "per_channel_us": b.per_channel_us[0], "margin_us": b.margin_us}
        for name, b in both.items()
    }


def latencies(phases: int) -> dict[str, dict[str, dict[str, float]]]:
    def trim(d: dict[str, float | None]) -> dict[str, float]:
        return {k: round(float(v), 1) for k, v in d.items() if v is not None}

    v12 = pattern_latency(
        ScanConfig.make(32, 1, pulse_width_us=200, pulse_height=100, discharge_us=45, rate_hz=125),
        "usb",
        phases=phases,
    )
    out = {
        "v1.2 usb": {
            "first_channel_us": trim(v12["first_channel_us"]),
            "last_channel_us": trim(v12["last_channel_us"]),
        }
    }
    for chunking in ("whole", "upstream"):
        r = pattern_in_force_v2([100] * 32, phases=phases, chunking=chunking)
        out[f"v2 usb {chunking}"] = {
            "first_channel_us": trim(r["first_channel_us"]),
            "last_channel_us": trim(r["last_channel_us"]),
        }
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument(
        "--phases", type=int, default=16, help="write moments spread over one period (default 16)"
    )
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()
    result = {
        "v2_vectors": vectors_matched(),
        "budget_tactdeform": budgets(),
        "pattern_in_force": latencies(args.phases),
    }
    if args.json:
        print(json.dumps(result, indent=2))
        return 0
    v = result["v2_vectors"]
    print(f"v2 golden vectors matched: {v['matched']} / {v['total']}")
    print("TactDeform setting (32 electrodes, 200 us, discharge 45 us, 125 Hz):")
    for k, b in result["budget_tactdeform"].items():
        print(
            f"  {k:<16} scan {b['scan_us']:8.2f} us  per channel {b['per_channel_us']:7.2f} us  margin "
            f"{b['margin_us']:7.2f} us"
        )
    print("host write -> pattern in force, one frame of 32 per-electrode intensities (min / mean / max, us):")
    for k, d in result["pattern_in_force"].items():
        f, last = d["first_channel_us"], d["last_channel_us"]
        print(
            f"  {k:<18} first channel {f['min']:.0f} / {f['mean']:.0f} / {f['max']:.0f}   "
            f"last channel {last['min']:.0f} / {last['mean']:.0f} / {last['max']:.0f}"
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
