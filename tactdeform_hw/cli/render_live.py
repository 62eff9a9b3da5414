"""``tactdeform-hw render --tracking URL``: the live half of ``render``.

The source (and the LSL outlet) are opened before the device, so a port in use or a missing extra sends
nothing.  The run ends with Ctrl-C or another stop signal: the stop handler has switched every channel off
by the time it reaches here; the device is closed (all off again), the summary printed (``--json``: one
object, latency included), and the stop passed on, so the command ends with the signal's status (130 for
Ctrl-C) and its one line on stderr, as every stimulating command does.
"""

from __future__ import annotations

import argparse
import json
import sys
from typing import IO, Any

from .common import print_json, progress


def stim_config_of(args: argparse.Namespace, session: Any) -> Any:
    """The participant's calibrated pulse (the guard refuses anything else), or None without a profile."""
    profile = session.profile
    if profile is None:
        return None
    from ..device import StimConfig

    return StimConfig(
        electrode_count=session.wiring.mapping.hw_channels,
        current_ua=args.current_ua,
        pulse_width_us=profile.pulse_width_us,
        polarity=profile.polarity,
    )


def renderer_of(args: argparse.Namespace, session: Any, scene: Any, dev: Any) -> tuple[Any, bool]:
    """The command line's renderer on ``dev``, and whether it reads each sent frame back: an instant port
    holds its pattern the moment it is sent, so it is read back when the port can show it."""
    from ..ports import is_instant

    verify = session.readback(dev) if is_instant(getattr(dev, "port", None)) else None
    renderer = session.renderer(
        scene,
        dev,
        approach=args.approach,
        contact_mode=args.contact_mode,
        current_ua=args.current_ua,
        stim_config=stim_config_of(args, session),
        verify=verify,
    )
    return renderer, verify is not None


class _Files:
    """``--frames`` and ``--latency-report``, written line by line as the run goes."""

    def __init__(self, frames: str | None, report: str | None) -> None:
        self.frames: IO[str] | None = None
        self.report: IO[str] | None = None
        self.frames = open(frames, "w", encoding="utf-8") if frames else None  # noqa: SIM115
        self.report = open(report, "w", encoding="utf-8") if report else None  # noqa: SIM115

    def record(self, rec: Any) -> None:
        if self.frames is not None:
            self.frames.write(json.dumps(rec.to_json(), separators=(",", ":")) + "\n")

    def timing(self, t: Any) -> None:
        if self.report is not None:
            self.report.write(json.dumps(t.to_json(), separators=(",", ":")) + "\n")

    def close(self) -> None:
        for f in (self.frames, self.report):
            if f is not None:
                f.close()


def run_live(args: argparse.Namespace, session: Any, scene: Any) -> int:
    from ..render.live import LslPatternOutlet, open_tracking

    scene.prepare()
    outlet = LslPatternOutlet(args.lsl_out, session.wiring.array.count) if args.lsl_out else None
    source = open_tracking(args.tracking)
    files: _Files | None = None
    audit = None
    try:
        files = _Files(args.frames, args.latency_report)
        audit = session.delivery_log(session.header("render"), requested_ua=args.current_ua)
        live, verified, stopped = _drive_live(args, session, scene, source, outlet, files)
    finally:
        source.close()
        if files is not None:
            files.close()
        if audit is not None:
            audit.close()
    summary = live.renderer.summary
    result = summary.as_dict()
    result["delivered"] = audit.report()
    result["live"] = dict(live.result.stats.as_dict(), stream_stops=live.result.stream_stops)
    result["latency"] = live.result.latency()
    result.update(
        {
            "scene": args.scene,
            "tracking": source.name,
            "verified": verified,
            "device": args.device,
            "frames_file": args.frames,
            "latency_report": args.latency_report,
            "lsl_out": args.lsl_out,
            "approach": scene.options.approach,
            "contact_mode": scene.options.contact_mode,
        }
    )
    if args.json:
        print_json(result)
    else:
        _print(result)
    sys.stdout.flush()
    if stopped is not None:
        raise stopped
    return 1 if verified and summary.mismatches else 0


def _drive_live(
    args: argparse.Namespace, session: Any, scene: Any, source: Any, outlet: Any, files: _Files
) -> tuple[Any, bool, BaseException | None]:
    """Open the device and render the source until a stop: the run, whether frames were read back, and the
    stop (every channel is off by then; the device closes here, all off again)."""
    from tactdeform_hw.device.safety.failsafe import SignalStop

    from ..render.live import LiveRun

    stopped: BaseException | None = None
    with session.open_device() as dev:
        renderer, verified = renderer_of(args, session, scene, dev)
        live = LiveRun(
            renderer,
            source,
            on_record=files.record,
            on_status=None if args.quiet else progress,
            on_timing=files.timing,
            outlet=outlet,
        )
        if not args.quiet:
            progress(
                f"render: live from {source.name} over {args.scene}, approach "
                f"{args.approach or scene.options.approach}, device {args.device}; Ctrl-C ends the run"
            )
        try:
            live.run()
        except (KeyboardInterrupt, SignalStop) as stop:
            stopped = stop
    return live, verified, stopped


def _print(result: dict[str, Any]) -> None:
    from .delivered import delivered_lines

    live, lat = result["live"], result["latency"]
    states = ", ".join(f"{k} {v}" for k, v in sorted(result["states"].items())) or "none"
    print(
        f"{live['received']} samples received ({live['valid']} valid, {live['bad_total']} bad "
        f"{live['bad']}), lost {live['lost']} ({live['loss_pct']} %), jitter {live['jitter_ms']} ms; "
        f"{result['poses']} rendered ({states}); {result['frames_sent']} frames sent"
    )
    for stage, d in lat.items():
        if d["n"]:
            print(
                f"{stage.replace('_', ' ')}: median {d['median_ms']} ms, p99 {d['p99_ms']} ms, "
                f"max {d['max_ms']} ms ({d['n']} samples)"
            )
    if result["lost_tracking"]:
        print(
            f"tracking lost {result['lost_tracking']} time(s) ({live['stream_stops']} stream stop(s)): all "
            f"off; {result['held_resuming']} valid sample(s) held back before stimulation resumed"
        )
    for line in delivered_lines(result["delivered"]):
        print(line)
