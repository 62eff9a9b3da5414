"""``tactdeform-hw render``: run a synthetic study trajectory over a scene through the renderer to a
device, and write every frame the device held.

    tactdeform-hw render --scene cube --trajectory approach-face --approach tactdeform \\
        --device emulator --frames frames.jsonl

Or render a live hand tracker as its samples arrive (``--tracking udp://HOST:PORT`` or
``lsl://STREAM_NAME``, see :mod:`tactdeform_hw.render.live`) until Ctrl-C, which switches everything off,
prints the summary (stream figures and latency included) and exits with status 130.

Each line of the frames file is one pattern: ``t`` (s), ``state`` (idle / approaching / interacting),
``feature``, ``texture``, ``electrodes`` (32 ints in application order, 0 off, 1 on) and ``sent``
(whether a command went to the device).  With the emulator, every sent frame is compared with the
emulator's pattern buffer; any mismatch makes the command exit with status 1.
"""

from __future__ import annotations

import argparse
import json
import sys
from typing import Any

from .common import add_device_arg, add_participant_arg, print_json, progress, session_from_args
from .options import add_option, add_tracking_rate
from .outputs import writing


def register(sub: Any) -> None:
    p: argparse.ArgumentParser = sub.add_parser(
        "render",
        help="render a study trajectory over a scene to a device (emulator by default)",
        description="Drive a device with the TactDeform renderer (or the UA / CAM baselines) along a "
        "synthetic study trajectory over a scene. The device is configured once and sent a pattern only "
        "when it changes. --frames writes one JSON line per pattern held; with the emulator every sent "
        "pattern is checked against the emulator's pattern buffer and any mismatch exits with status 1.",
    )
    _trajectory_options(p)
    _rendering_options(p)
    _output_options(p)
    p.set_defaults(func=run)


def _trajectory_options(p: argparse.ArgumentParser) -> None:
    """The scene and the finger's trajectory over it."""
    from ..render.trajectories import TRAJECTORIES

    p.add_argument(
        "--scene",
        required=True,
        help="sphere, cube, teapot, bunny, task1, task2, task3, a mesh file (OBJ/STL/PLY) or a scene "
        "description (.toml/.json)",
    )
    p.add_argument(
        "--trajectory",
        default=None,
        metavar="NAME|FILE.csv",
        help="a synthetic trajectory (" + ", ".join(TRAJECTORIES) + ") or a recorded one: a CSV with the "
        "header t_s,x_mm,y_mm,z_mm,qw,qx,qy,qz (world mm; the quaternion turns the pad frame — x right, "
        "y toward the fingertip, z out of the pad — into the world)",
    )
    p.add_argument(
        "--invalid-rows",
        choices=("error", "replay"),
        default=None,
        help="a recorded trajectory's rows that are no valid pose (NaN or infinite values, a quaternion that "
        "is not a rotation, a time that does not advance): 'error' (default) stops before anything is sent, "
        "naming the row; 'replay' hands every row to the renderer as the tracker delivered it, so its "
        "lost-tracking rules decide (dropped rows never keep stimulation on; after lost tracking it resumes "
        "only after a run of valid samples) and the summary counts them",
    )
    _live_options(p)
    add_option(
        p,
        "--speed-mm-s",
        old=("--speed",),
        dest="speed",
        metavar="MM_S",
        type=float,
        default=None,
        help="finger speed in mm/s (default: the trajectory's own; synthetic only)",
    )
    add_tracking_rate(p, default=None, help="tracking rate in Hz (default 72, the VR loop; synthetic only)")


def _live_options(p: argparse.ArgumentParser) -> None:
    """A live tracker instead of a trajectory."""
    p.add_argument(
        "--tracking",
        metavar="URL",
        default=None,
        help="render a live tracker instead of --trajectory: udp://HOST:PORT (one sample per datagram, UTF-8 "
        "text t_s,x_mm,y_mm,z_mm,qw,qx,qy,qz, optionally after that header line) or lsl://STREAM_NAME (eight "
        "channels, needs the lsl extra). Bad samples are counted, never rendered; a stream that stops turns "
        "stimulation off; runs until Ctrl-C (exit status 130 after the summary)",
    )
    p.add_argument(
        "--latency-report",
        metavar="FILE",
        default=None,
        help="with --tracking: one JSON line per valid sample: time.monotonic() when it was received, its "
        "pattern computed and its bytes written, and the patterns sent",
    )
    p.add_argument(
        "--lsl-out",
        metavar="NAME",
        default=None,
        help="publish every pattern sent as the LSL stream NAME (t_s, state, feature, each electrode's "
        "current in µA; needs the lsl extra)",
    )


def _rendering_options(p: argparse.ArgumentParser) -> None:
    """How the contact is rendered, on which device, for which participant."""
    from ..render.scene import APPROACHES, CONTACT_MODES

    p.add_argument(
        "--approach",
        choices=APPROACHES,
        default=None,
        help="rendering approach (default: the scene's, tactdeform)",
    )
    p.add_argument(
        "--contact-mode",
        choices=CONTACT_MODES,
        default=None,
        help="stationary contact: orientation-specific shift (eq. 4) or uniform (default: the scene's, "
        "orientation)",
    )
    add_device_arg(p)
    add_participant_arg(p)


def _output_options(p: argparse.ArgumentParser) -> None:
    """What the run writes and shows."""
    p.add_argument("--frames", metavar="FILE", default=None, help="write the frames as JSON lines to FILE")
    p.add_argument(
        "--gif",
        metavar="OUT.gif",
        default=None,
        help="also draw the held patterns on the array as an animated GIF, "
        "each frame shown at least 250 ms with its real time on it (needs the plot extra)",
    )
    p.add_argument(
        "--strip",
        metavar="OUT.png",
        default=None,
        help="also draw the sent frames side by side in a PNG (needs the plot extra)",
    )
    p.add_argument(
        "--current-ua",
        type=int,
        default=None,
        help="participant current in µA (default: the highest calibrated region with --participant, else 0: "
        "patterns only)",
    )
    p.add_argument("--seed", type=int, default=0, help="seed of the trajectory's random parts (default 0)")
    p.add_argument("--realtime", action="store_true", help="pace the run to the trajectory's clock")
    p.add_argument("--json", action="store_true", help="print the run summary as JSON")
    p.add_argument("--quiet", action="store_true", help="no progress on stderr")


def _check_options(args: argparse.Namespace) -> bool:
    """Refuse options that do not fit the trajectory; whether it is a recorded one (a CSV file)."""
    from ..errors import LimitError
    from ..render.trajectories import TRAJECTORIES

    if (args.trajectory is None) == (args.tracking is None):
        raise LimitError(
            "--trajectory" if args.trajectory is None else "--tracking",
            args.trajectory if args.trajectory is not None else args.tracking,
            "exactly one of --trajectory NAME|FILE.csv and --tracking URL",
        )
    if args.tracking is not None:
        _check_live(args)
        return True
    if args.latency_report is not None:
        raise LimitError("--latency-report", args.latency_report, "a live run (--tracking URL)")
    recorded = args.trajectory not in TRAJECTORIES
    if recorded and not args.trajectory.lower().endswith(".csv"):
        raise LimitError(
            "--trajectory", args.trajectory, "one of " + ", ".join(TRAJECTORIES) + " or a recorded FILE.csv"
        )
    if recorded and (args.speed is not None or args.rate is not None):
        raise LimitError(
            "--speed" if args.speed is not None else "--rate",
            args.speed if args.speed is not None else args.rate,
            "not applicable to a recorded trajectory (it has its own clock and speed)",
        )
    if not recorded and args.invalid_rows is not None:
        raise LimitError(
            "--invalid-rows", args.invalid_rows, "a recorded FILE.csv trajectory (a synthetic one has none)"
        )
    args.rate = 72.0 if args.rate is None else args.rate
    if not args.rate > 0 or args.rate != args.rate:
        raise LimitError("--rate", args.rate, "> 0 Hz")
    if args.speed is not None and (not args.speed > 0 or args.speed == float("inf")):
        raise LimitError("--speed", args.speed, "a finite speed > 0 mm/s")
    return recorded


def _check_live(args: argparse.Namespace) -> None:
    """Refuse the trajectory-only options with --tracking."""
    from ..errors import LimitError

    for name, value in (
        ("--speed-mm-s", args.speed),
        ("--rate-hz", args.rate),
        ("--invalid-rows", args.invalid_rows),
        ("--gif", args.gif),
        ("--strip", args.strip),
    ):
        if value is not None:
            raise LimitError(name, value, "a --trajectory run (a live tracker has its own clock and no end)")
    if args.realtime:
        raise LimitError("--realtime", True, "a --trajectory run (a live run is real time by nature)")


def _current(args: argparse.Namespace, session: Any) -> None:
    """The participant's current and contact mode where the command line gives none; an unsafe current is
    refused here, before the device is opened."""
    from ..errors import LimitError
    from ..protocol.units import DEFAULT_TRANSFER

    profile = session.profile
    if profile is not None:
        args.current_ua = profile.stimulation_ua if args.current_ua is None else args.current_ua
        args.contact_mode = args.contact_mode or profile.contact_mode
    args.current_ua = 0 if args.current_ua is None else args.current_ua
    if args.current_ua < 0:
        raise LimitError("--current-ua", args.current_ua, "≥ 0 µA")
    guard = session.guard
    guard.request(guard.validate_current(args.current_ua, DEFAULT_TRANSFER))  # above the cap: refused


def _scene(args: argparse.Namespace, recorded: bool) -> Any:
    """The scene, with the options the command line gives replacing only their own fields."""
    from ..render.scene import RenderOptions, load_scene
    from ..render.trajectories import scene_for_trajectory

    scene = load_scene(args.scene)
    if args.approach is not None or args.contact_mode is not None:
        own = scene.options
        scene = scene.with_options(
            RenderOptions(
                contact_mode=args.contact_mode or own.contact_mode, approach=args.approach or own.approach
            )
        )
    # A slide needs a surface of its texture level; the trajectory module gives a scene that has one.
    return scene if recorded else scene_for_trajectory(args.trajectory, scene)


def _poses(args: argparse.Namespace, scene: Any, recorded: bool) -> list[Any]:
    """The finger's poses: a recorded trajectory's rows, or a synthetic one planned over ``scene``."""
    from ..errors import LimitError
    from ..render.scene import RenderOptions
    from ..render.trajectories import make_trajectory

    if recorded:
        from ..render.tracking import read_pose_csv, read_pose_rows

        poses: list[Any]
        if args.invalid_rows == "replay":
            poses = list(read_pose_rows(args.trajectory))  # only a cell that is no number is an error
        else:
            poses = list(read_pose_csv(args.trajectory))  # a bad row is an error naming its line and column
        if not poses:
            raise LimitError("--trajectory", args.trajectory, "a CSV with at least one pose row")
        refuse_metres(args.trajectory, poses)
        return poses
    # The finger's path is geometry: plan it where faces, edges and corners are classified, whatever
    # approach renders it (the baselines' scenes do not classify features).
    plan = scene
    if scene.options.approach != "tactdeform":
        plan = scene.with_options(
            RenderOptions(contact_mode=scene.options.contact_mode, approach="tactdeform")
        )
    kw: dict[str, Any] = {"rate_hz": args.rate, "seed": args.seed}
    if args.speed is not None:
        kw["speed_mm_s"] = args.speed
    return list(make_trajectory(args.trajectory, plan, **kw))


#: Positions whose magnitudes all stay under this (mm) while they move read as metres: a finger that
#: never leaves a 2 mm ball around the scene's origin is no trajectory a study records.
METRES_BOUND_MM = 2.0


def refuse_metres(path: str, poses: list[Any]) -> None:
    """Refuse a recorded trajectory whose positions look like metres (every coordinate under
    :data:`METRES_BOUND_MM` in magnitude, and moving): read as millimetres it never comes near the object,
    and the render would report idle poses and no frame without saying why."""
    import math

    from ..errors import ConfigurationError

    # a Pose, or a replayed row ``(t_s, position_mm, orientation)`` (NaN rows kept for the lost-tracking
    # rules: left out here)
    rows = [p.position_mm if hasattr(p, "position_mm") else p[1] for p in poses]
    coords = [[float(v) for v in row] for row in rows if all(math.isfinite(float(v)) for v in row)]
    if not coords:
        return
    largest = max(abs(v) for row in coords for v in row)
    moving = any(row != coords[0] for row in coords)
    if not moving or largest == 0 or largest >= METRES_BOUND_MM:
        return
    row, col = max(
        ((r, c) for r in range(len(coords)) for c in range(3)), key=lambda rc: abs(coords[rc[0]][rc[1]])
    )
    column = ("x_mm", "y_mm", "z_mm")[col]
    raise ConfigurationError(
        f"--trajectory {path}: the positions look like metres, not millimetres (the largest, {column} = "
        f"{coords[row][col]:g} in pose row {row + 1}, is under {METRES_BOUND_MM:g} mm); the x_mm, y_mm, z_mm "
        "columns take millimetres: multiply them by 1000"
    )


def _drive(
    args: argparse.Namespace, session: Any, scene: Any, poses: list[Any], on_record: Any
) -> tuple[Any, bool]:
    """Open the device, render every pose to it; the run's summary and whether frames were read back."""
    from .render_live import renderer_of

    offline_clock = None
    if not args.realtime:
        # on a port that answers at once (the in-process emulator) the session runs on the trajectory's clock
        from ..clock import SimulatedClock

        offline_clock = SimulatedClock()
    total, quiet = len(poses), args.quiet

    def report(i: int, s: Any) -> None:
        if not quiet:
            progress(f"render: {i}/{total} poses, {s.frames_sent} frames sent, {s.mismatches} mismatches")

    with session.open_device(offline_clock=offline_clock) as dev:
        renderer, verified = renderer_of(args, session, scene, dev)
        every = max(1, total // 10) if total > 2000 else total + 1
        summary = renderer.run(
            poses, on_record=on_record, progress=report, progress_every=every, realtime=args.realtime
        )
    return summary, verified


def _pictures(
    args: argparse.Namespace, array: Any, records: list[dict[str, Any]], result: dict[str, Any]
) -> None:
    """``--gif`` and ``--strip``: the held patterns drawn on the array."""
    title = f"{args.trajectory} over {args.scene}"
    if args.gif:
        from ..viz.array_picture import draw_frames_gif

        gif = draw_frames_gif(array, records, args.gif, current_ua=args.current_ua or None, title=title)
        result["gif"] = {"path": str(gif.path), "frames": gif.frames, "notes": list(gif.notes)}
    if args.strip:
        from ..viz.strip import draw_frames_strip

        strip = draw_frames_strip(array, records, args.strip, title=title)
        result["strip"] = {"path": str(strip.path), "panels": strip.panels, "left_out": strip.left_out}


def _print_result(result: dict[str, Any], summary: Any, verified: bool) -> None:
    from .delivered import delivered_lines

    states = ", ".join(f"{k} {v}" for k, v in sorted(result["states"].items()))
    check = f", {summary.mismatches} mismatch(es) against the emulator" if verified else ""
    print(
        f"{result['poses']} poses ({states}); {result['frames_sent']} frames sent "
        f"({result['interpolated']} interpolated){check}; median {result['step_us_median']} µs per pose"
    )
    if result["dropped"]:
        print(f"dropped samples: {result['dropped']}")
    if result["lost_tracking"]:
        print(
            f"tracking lost {result['lost_tracking']} time(s): all off; {result['held_resuming']} valid "
            "sample(s) held back before stimulation resumed"
        )
    for line in delivered_lines(result["delivered"]):
        print(line)


def run(args: argparse.Namespace) -> int:
    from ..render.pipeline import FrameRecord
    from ..session import Wiring

    recorded = _check_options(args)
    # a bad profile is refused before anything is opened; regional limits follow the positions of the
    # array the renderer draws on
    session = session_from_args(args, Wiring.tactdeform())
    _current(args, session)
    if args.tracking is not None:
        from .render_live import run_live

        return run_live(args, session, _scene(args, True))
    scene = _scene(args, recorded)
    poses = _poses(args, scene, recorded)
    scene.prepare()
    if not args.quiet:
        progress(
            f"render: {args.trajectory} over {args.scene}{'' if recorded else f' at {args.rate:g} Hz'}, "
            f"{len(poses)} poses, approach {args.approach or scene.options.approach}, device {args.device}"
        )
    out = open(args.frames, "w", encoding="utf-8") if args.frames else None  # noqa: SIM115
    records: list[dict[str, Any]] | None = [] if (args.gif or args.strip) else None

    def write(rec: FrameRecord) -> None:
        if out is not None:
            with writing("--frames", args.frames):
                out.write(json.dumps(rec.to_json(), separators=(",", ":")) + "\n")
        if records is not None:
            records.append(rec.to_json())

    audit = None
    try:
        audit = session.delivery_log(session.header("render"), requested_ua=args.current_ua)
        summary, verified = _drive(args, session, scene, poses, write)
    finally:
        if out is not None:
            with writing("--frames", args.frames):
                out.close()
        if audit is not None:
            audit.close()
    result = summary.as_dict()
    result["delivered"] = audit.report()
    result.update(
        {
            "scene": args.scene,
            "trajectory": args.trajectory,
            "rate_hz": None if recorded else args.rate,
            "verified": verified,
            "device": args.device,
            "frames_file": args.frames,
            "approach": scene.options.approach,
            "contact_mode": scene.options.contact_mode,
        }
    )
    if records is not None:
        _pictures(args, session.wiring.array, records, result)
    if args.json:
        print_json(result)
    else:
        _print_result(result, summary, verified)
    if verified and summary.mismatches:
        print(
            f"render: emulator pattern buffer differs from a sent frame: {summary.first_mismatch}",
            file=sys.stderr,
        )
        return 1
    return 0
