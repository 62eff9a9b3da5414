"""``tactdeform-hw timing --firmware-src``: the scan budget, events, VCD and picture of the built firmware.

The Python timing command computes a configuration's budget from the timing model's reading of the
firmware.  With a host build the firmware itself runs: it is configured through its own parser (the wire
bytes a driver sends), runs its scans in virtual time, and the budget is measured on them: each scan's
duration is its interrupt handler's run (entry to return), the period is the firmware's own
``StimulationTimePeriod``, the margin is the period less the longest scan, and an overrun is a scan longer
than the period.  The events are the host build's GPIO and DAC events, in the golden traces' conventions
(:meth:`.emulator.HostBuildEmulator.events`).
"""

from __future__ import annotations

import json
import os
import struct
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from tactdeform_hw.emulator.hostbuild.delivered import ETACTILEKIT_PINS
from tactdeform_hw.emulator.hostbuild.emulator import HostBuildEmulator
from tactdeform_hw.emulator.hostbuild.statemap import StateMap
from tactdeform_hw.emulator.timed.timing import TimingModel
from tactdeform_hw.errors import ConfigurationError, LimitError
from tactdeform_hw.protocol.firmware import Opcode, OpcodeV2

#: When the configuration is written: after the boot's stack detection (50 readings, 1 ms) and its set-up.
CONFIGURE_AT_US = 2000.0

#: How long the firmware may take to read the configuration before the scans are counted (µs): one
#: command with a payload per 1 ms RTOS tick, a dozen commands.
CONFIGURE_SETTLE_US = 20_000.0


def wire_v1_2(
    electrode_num: int,
    pattern: bytes,
    *,
    frequency_hz: int,
    pulse_height: int,
    pulse_width_us: int,
    sense_height_code: int,
    sense_width_us: int,
    discharge_us: int,
    polarity: int,
) -> bytes:
    """The v1.2 commands that set a configuration (the payloads as the protocol sends them; the sense
    height as its stored DAC code, sent shifted right by 2)."""
    o = Opcode
    b = bytearray([o.FREQUENCY]) + struct.pack("<H", frequency_hz)
    b += bytes([o.ELECTRODE_NUM, electrode_num])
    if electrode_num:
        b += bytes([o.PATTERN]) + bytes(pattern[:electrode_num])
    b += bytes([o.PULSE_HEIGHT]) + struct.pack("<H", pulse_height)
    if pulse_width_us:  # 0 is ignored by the parser (and is the power-on value)
        b += bytes([o.PULSE_WIDTH]) + struct.pack("<H", pulse_width_us)
    b += bytes([o.SENSE_HEIGHT, sense_height_code >> 2, o.SENSE_WIDTH, sense_width_us])
    b += bytes([o.DISCHARGE, discharge_us, o.POLARITY, polarity])
    return bytes(b)


def wire_v2(
    electrode_num: int,
    heights: list[int],
    *,
    frequency_hz: int,
    stim_mode: int,
    pulse_width_us: int,
    sense_height: int,
    sense_width_us: int,
    discharge_us: int,
    polarity: int,
) -> bytes:
    """The v2 commands that set a configuration (a u16 DAC code per electrode)."""
    o = OpcodeV2
    b = bytearray([o.FREQUENCY]) + struct.pack("<H", frequency_hz)
    b += bytes([o.ELECTRODE_NUM, electrode_num, o.STIM_MODE, stim_mode])
    if electrode_num:
        b += bytes([o.PATTERN]) + b"".join(struct.pack("<H", h) for h in heights[:electrode_num])
    b += bytes([o.PULSE_WIDTH]) + struct.pack("<H", pulse_width_us)
    b += bytes([o.SENSE_HEIGHT, sense_height, o.SENSE_WIDTH, sense_width_us])
    b += bytes([o.DISCHARGE, discharge_us, o.POLARITY, polarity])
    return bytes(b)


@dataclass(frozen=True)
class HostBuildBudget:
    """The measured budget: every counted scan (entry µs, return µs) and the firmware's period."""

    period_us: float
    scans: list[tuple[float, float]]
    firmware: str

    @property
    def scan_us(self) -> float:
        return max(b - a for a, b in self.scans)

    @property
    def margin_us(self) -> float:
        return self.period_us - self.scan_us

    @property
    def overrun(self) -> bool:
        return self.scan_us > self.period_us

    def to_dict(self) -> dict[str, Any]:
        durations = [b - a for a, b in self.scans]
        starts = [a for a, _ in self.scans]
        gaps = [b - a for a, b in zip(starts, starts[1:])]
        return {
            "source": "host build",
            "firmware": self.firmware,
            "period_us": self.period_us,
            "scan_us": {
                "min": min(durations),
                "max": max(durations),
                "mean": sum(durations) / len(durations),
            },
            "scan_interval_us": {"min": min(gaps), "max": max(gaps)} if gaps else None,
            "margin_us": self.margin_us,
            "overrun": self.overrun,
            "scans": len(self.scans),
        }

    def table(self) -> str:
        d = self.to_dict()
        lines = [
            f"Measured on the firmware's own code ({self.firmware}, host build), {d['scans']} scans:",
            f"  period (StimulationTimePeriod)   {self.period_us:>10.2f} µs",
            f"  scan (handler entry to return)   {d['scan_us']['max']:>10.2f} µs max, "
            f"{d['scan_us']['min']:.2f} min",
            f"  margin                           {self.margin_us:>10.2f} µs",
            f"  verdict                          {'OVERRUN' if self.overrun else 'fits'}",
        ]
        return "\n".join(lines)


def measure(
    firmware_src: str | os.PathLike[str],
    wire: bytes,
    cycles: int,
    *,
    hv513_count: int,
    timing: TimingModel | None = None,
    state_map: StateMap | None = None,
) -> tuple[HostBuildBudget, list[list[Any]], HostBuildEmulator]:
    """Configure the built firmware with ``wire`` and run until ``cycles`` scans after it settled; the
    budget, the events of those scans, and the emulator."""
    if not isinstance(cycles, int) or cycles < 1:
        raise LimitError("--cycles", cycles, "an integer >= 1")
    emu = HostBuildEmulator(firmware_src, hv513_count=hv513_count, timing=timing, state_map=state_map)
    emu.advance_to(CONFIGURE_AT_US)
    emu.write(wire, at_us=CONFIGURE_AT_US)
    settled = CONFIGURE_AT_US + CONFIGURE_SETTLE_US
    emu.advance_to(settled)
    state = emu.state()
    if "period_us" not in state:
        raise ConfigurationError("--firmware-src: the tree's state map names no period_us register")
    period = float(state["period_us"])
    step = max(period, 1000.0)
    limit = settled + (cycles + 2) * step * 4
    while len([s for s in emu.scans() if s[0] >= settled]) < cycles:
        if emu.now_us >= limit:
            raise ConfigurationError(
                f"--firmware-src: {cycles} scan(s) expected within {limit / 1000:.1f} ms of virtual time; "
                f"the firmware ran {len([s for s in emu.scans() if s[0] >= settled])} (no electrodes?)"
            )
        emu.advance(step)
    counted = [s for s in emu.scans() if s[0] >= settled][:cycles]
    events = [e for e in emu.events(counted[0][0]) if e[0] <= counted[-1][1]]
    fw = emu.state_map.firmware if emu.state_map is not None and emu.state_map.firmware else "undeclared"
    return HostBuildBudget(period, counted, fw), events, emu


def write_events(path: str | os.PathLike[str], events: list[list[Any]]) -> None:
    """``.json``: the event list; ``.csv``: ``time_us,kind,pin,value`` rows (the timing command's formats)."""
    p = Path(path)
    try:
        if p.suffix.lower() == ".json":
            p.write_text(json.dumps(events) + "\n")
        else:
            p.write_text("time_us,kind,pin,value\n" + "".join(f"{t},{k},{n},{v}\n" for t, k, n, v in events))
    except OSError as exc:
        raise ConfigurationError(f"--events {str(p)!r}: cannot write: {exc}") from exc


_SIGNALS = {
    ETACTILEKIT_PINS.bl: "BL",
    ETACTILEKIT_PINS.le: "LE",
    ETACTILEKIT_PINS.pol: "POL",
    ETACTILEKIT_PINS.clk: "CLK",
    ETACTILEKIT_PINS.din: "DIN",
}


def write_vcd(path: str | os.PathLike[str], events: list[list[Any]]) -> None:
    """The board's pins (BL, LE, POL, CLK, DIN) and the DAC code as a VCD, 1 ns resolution."""
    try:
        from vcd import VCDWriter
    except ImportError as exc:
        raise ConfigurationError("--vcd needs pyvcd (pip install pyvcd)") from exc
    try:
        with open(path, "w", encoding="ascii") as fh, VCDWriter(fh, timescale="1 ns", date="today") as w:
            pins = {
                pin: w.register_var("etactilekit", name, "wire", size=1) for pin, name in _SIGNALS.items()
            }
            dac = w.register_var("etactilekit", "DAC", "integer", size=12)
            for t_us, kind, pin, value in events:
                t_ns = int(round(t_us * 1000))
                if kind == "GPIO" and pin in pins:
                    w.change(pins[pin], t_ns, int(value))
                elif kind == "DAC":
                    w.change(dac, t_ns, int(value))
    except OSError as exc:
        raise ConfigurationError(f"--vcd {str(path)!r}: cannot write: {exc}") from exc


def draw_png(path: str | os.PathLike[str], events: list[list[Any]], title: str) -> dict[str, Any]:
    """The pins and the DAC code against time, one row each."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = [*_SIGNALS.values(), "DAC"]
    fig, axes = plt.subplots(len(names), 1, sharex=True, figsize=(12, 6))
    for ax, name in zip(axes, names):
        if name == "DAC":
            pts = [(e[0], e[3]) for e in events if e[1] == "DAC"]
        else:
            pin = next(p for p, n in _SIGNALS.items() if n == name)
            pts = [(e[0], e[3]) for e in events if e[1] == "GPIO" and e[2] == pin]
        if pts:
            ts, vs = zip(*pts)
            ax.step(ts, vs, where="post", linewidth=0.8)
        ax.set_ylabel(name, rotation=0, labelpad=20)
    axes[-1].set_xlabel("µs (virtual time)")
    fig.suptitle(title)
    try:
        fig.savefig(path, dpi=100)
    except OSError as exc:
        raise ConfigurationError(f"--png {str(path)!r}: cannot write: {exc}") from exc
    finally:
        plt.close(fig)
    return {"path": str(path), "events": len(events)}


__all__ = ["HostBuildBudget", "draw_png", "measure", "wire_v1_2", "wire_v2", "write_events", "write_vcd"]
