"""``tactdeform-hw study``: run a TactDeform study's trials through the whole pipeline and report what
each trial delivered.

    tactdeform-hw study task1 --device emulator --out runs/task1
    tactdeform-hw study phase2 --out runs/phase2 --participant p07.json --json

Every trial's synthetic finger poses go through tracking, the renderer, the driver and the port (the
emulator behind the virtual serial port by default); the bytes written are replayed into the timed
emulator for the currents and charges the scans delivered.  ``--out`` receives ``report.json``,
``summary.md``, the frames of every trial and pictures of the array.  Exit status: 0 when every check
passed, 3 when a check failed, 1 on an error (bad option, bad profile, no device).

Both firmware versions run it: the report names the one that ran, and on v2 (one height per electrode)
the checks also read every electrode's height back and the ``delivered`` section lists the heights each
electrode was pulsed at.
"""

from __future__ import annotations

import argparse
import math
import sys
from typing import Any

from ..errors import ConfigurationError
from .common import add_device_arg, add_participant_arg, print_json, progress, session_from_args
from .options import add_firmware_src, add_tracking_rate

EXIT_CHECK_FAILED = 3


def register(sub: Any) -> None:
    from ..study.scenarios import STUDIES, STUDY_TITLES

    p: argparse.ArgumentParser = sub.add_parser(
        "study",
        help="run a study's trials (task1, task2, task3, phase2) end to end and report what each delivered",
        description="Run the trials of one TactDeform study through tracking, the renderer, the driver and "
        "the device (the emulator by default), check what every trial delivered (the feature and "
        "texture rendered, the frames on the wire and in the emulator's pattern buffer, the "
        "pulses the scans delivered, hazards) and write a report to --out: report.json, "
        "summary.md, frames/ and pictures/. "
        + " ".join(f"{k}: {v.split(': ', 1)[-1]}." for k, v in STUDY_TITLES.items())
        + " Exit status 0 when every check passed, 3 when one failed or a trial was skipped (a missing "
        "mesh: its checks did not run).",
    )
    p.add_argument("study", choices=STUDIES, help="which study to run")
    add_device_arg(p)
    add_participant_arg(p)
    p.add_argument("--out", required=True, metavar="DIR", help="directory for the report (created if needed)")
    p.add_argument(
        "--seed",
        type=int,
        default=0,
        help="seed of the trial order and of the seeded choices of the design (default 0)",
    )
    p.add_argument(
        "--quick",
        action="store_true",
        help="one trial per condition (and faster strokes for task3 and phase2): a setup check in seconds",
    )
    p.add_argument(
        "--trials",
        metavar="LIST",
        default=None,
        help="run only these trials: numbers and ranges (1-3,8) or conditions (face,edge-h)",
    )
    p.add_argument(
        "--current-ua",
        type=int,
        default=None,
        help="stimulation current in µA (default: the participant's; without one, 1000 µA on the "
        "emulator so delivered charges are reported, 0 — patterns only — on a real device)",
    )
    add_tracking_rate(p, default=72.0, help="tracking rate in Hz (default 72, the VR loop)")
    p.add_argument(
        "--tremor-mm",
        type=float,
        default=0.0,
        help="add physiological tremor of this amplitude to every trajectory (default 0: none)",
    )
    p.add_argument(
        "--realtime",
        action="store_true",
        help="pace the run to the session clock, so a real device shows every trial at its real speed "
        "(default: as fast as possible; the timed replay restores the timing for the checks)",
    )
    p.add_argument(
        "--no-timed", action="store_true", help="skip the timed-emulator replay (no delivered currents)"
    )
    _replay_options(p)
    p.add_argument("--no-pictures", action="store_true", help="write the JSON and Markdown only")
    p.add_argument("--gif", action="store_true", help="also draw every trial as an animated GIF (slower)")
    p.add_argument("--json", action="store_true", help="print the report's summary as JSON on stdout")
    p.add_argument("--quiet", action="store_true", help="no progress on stderr")
    p.add_argument(
        "--force",
        action="store_true",
        help="reuse an --out that holds an earlier report: its report.json, summary.md, trials.jsonl, "
        "frames/ and pictures/ are removed first (other files stay). Without --force such a directory is "
        "refused before the device is opened",
    )
    p.set_defaults(func=run)


def _replay_options(p: argparse.ArgumentParser) -> None:
    """Where the timed replay runs."""
    add_firmware_src(
        p,
        help="replay the session's writes into this firmware tree (PlatformIO) built on this machine instead "
        "of the Python timed model: what the firmware's own code delivered (docs/firmware-host-build.md); "
        "its state map must declare the version the session ran",
    )


def run(args: argparse.Namespace) -> int:
    from ..protocol.units import DEFAULT_TRANSFER
    from ..session import Wiring
    from ..study.checks import check_study
    from ..study.report import TrialLog, clear_earlier_report, write_report
    from ..study.runner import run_study
    from ..study.scenarios import build_study, select_trials

    _check_options(args)
    # A bad profile, study or trial list is refused before the device is opened; regional limits follow
    # the positions of the array the renderer draws on.
    session = session_from_args(args, Wiring.tactdeform())
    profile = session.profile
    mode = profile.contact_mode if profile is not None else "orientation"
    study = select_trials(
        build_study(args.study, seed=args.seed, quick=args.quick, contact_mode=mode), args.trials
    )
    if args.current_ua is not None:
        # above the cap: refused before opening
        session.guard.request(session.guard.validate_current(args.current_ua, DEFAULT_TRANSFER))
    audit = session.delivery_log(session.header("study", study=args.study), requested_ua=args.current_ua)
    say = (lambda _m: None) if args.quiet else progress
    say(
        f"study {study.name}: {len(study.trials)} trial(s){' (quick)' if study.quick else ''}, device "
        f"{args.device}, seed {args.seed}"
    )
    if args.force:
        clear_earlier_report(args.out)
    trial_log = TrialLog(args.out, study)
    try:
        with audit:
            result = run_study(
                study,
                session=session,
                rate_hz=args.rate,
                current_ua=args.current_ua,
                timed=not args.no_timed,
                firmware_src=args.firmware_src,
                tremor_mm=args.tremor_mm,
                progress=say,
                realtime=args.realtime,
                on_trial=trial_log,
            )
    except BaseException as exc:  # Ctrl-C, a stop signal, an error: keep what ran, say what did not
        why = "stopped by a signal" if isinstance(exc, (KeyboardInterrupt, SystemExit)) else f"error: {exc}"
        trial_log.interrupted(why)
        say(
            f"study {study.name}: {why} after {len(trial_log.done)} of {len(study.trials)} trial(s); "
            f"partial report in {args.out}/report.json"
        )
        raise
    result.sent = audit.report()
    result.sent["requested_ua"] = result.current_ua
    result.sent["firmware"] = result.firmware
    if result.heights_per_electrode:
        result.sent["electrode_heights_ua"] = electrode_heights(result)
    design = check_study(result)
    say(f"study {study.name}: writing the report to {args.out}")
    report = write_report(result, design, args.out, pictures=not args.no_pictures, gif=args.gif)
    s = report["summary"]
    if args.json:
        print_json(_json_summary(args, study, result, report))
    else:
        _print_summary(args, study, result, s)
    if not s["all_passed"]:
        if not args.quiet:
            _print_not_passed(study, result, s)
        return EXIT_CHECK_FAILED
    return 0


def _check_options(args: argparse.Namespace) -> None:
    """The options refused before anything is read or opened, ``--out`` among them: an earlier report
    there is refused without ``--force`` (its old frames and pictures would sit beside the new ones)."""
    from ..errors import LimitError
    from ..study.report import earlier_report

    if not (math.isfinite(args.rate) and args.rate > 0):
        raise LimitError("--rate", args.rate, "a finite rate > 0 Hz")
    if args.current_ua is not None and args.current_ua < 0:
        raise LimitError("--current-ua", args.current_ua, "≥ 0 µA")
    if not (math.isfinite(args.tremor_mm) and 0 <= args.tremor_mm <= 5):
        raise LimitError("--tremor-mm", args.tremor_mm, "0 to 5 mm")
    if args.firmware_src is not None:
        from ..emulator.hostbuild.statemap import declared_firmware

        declared = declared_firmware(args.firmware_src, "--firmware-src")
        if args.no_timed:
            raise ConfigurationError(
                "--firmware-src runs the timed replay on the built firmware; drop --no-timed"
            )
        if declared not in ("v1.2", "v2") or args.firmware not in ("auto", declared):
            needs = "v1.2 or v2" if args.firmware == "auto" else args.firmware
            raise ConfigurationError(
                f"--firmware-src {args.firmware_src}: its state map declares firmware "
                f"{declared or 'none'}; the study needs {needs}; nothing was sent"
            )
    old = earlier_report(args.out)
    if old and not args.force:
        raise ConfigurationError(
            f"--out {args.out}: holds an earlier report ({', '.join(old)}); give --force to replace it or "
            "another directory; nothing was sent"
        )


def _print_not_passed(study: Any, result: Any, s: dict[str, Any]) -> None:
    """stderr's line for a study that did not pass: the failed checks, or the trials skipped and why."""
    failed = "" if not (s["failed"] or not s["design_ok"]) else ", ".join(s["failed_checks"]) or "design"
    print(
        f"study {study.name}: "
        + (f"checks failed: {failed}" if failed else f"{s['skipped']} trial(s) skipped")
        + "".join(f"; {n}" for n in result.notes if not failed and "skipped" in n),
        file=sys.stderr,
    )


def _json_summary(
    args: argparse.Namespace, study: Any, result: Any, report: dict[str, Any]
) -> dict[str, Any]:
    """The ``--json`` of a study: the report's summary, what was delivered, each trial's verdict."""
    return {
        "study": study.name,
        "out": args.out,
        "summary": report["summary"],
        "design_checks": report["design_checks"],
        "delivered": result.sent,
        "pictures": report.get("pictures"),
        "trials": [
            {
                "id": t["id"],
                "passed": t["passed"],
                "skipped": t["skipped"],
                "failed_checks": t.get("failed_checks", []),
            }
            for t in report["trials"]
        ],
    }


def _print_summary(args: argparse.Namespace, study: Any, result: Any, s: dict[str, Any]) -> None:
    """The console's account of a study: the verdict, the failed checks, what was delivered."""
    from .delivered import delivered_lines

    verdict = (
        "all checks passed"
        if s["all_passed"]
        else f"{s['failed']} trial(s) FAILED"
        if s["failed"] or not s["design_ok"]
        else f"INCOMPLETE: {s['skipped']} trial(s) not run, so not every check passed"
    )
    print(
        f"{study.name}: {s['passed']}/{s['run']} trial(s) passed"
        + (f", {s['skipped']} skipped" if s["skipped"] else "")
        + f" — {verdict}; report in {args.out}/report.json and {args.out}/summary.md"
    )
    for name, n in s["failed_checks"].items():
        print(f"  failed: {name} ({n} trial(s))")
    for line in delivered_lines(result.sent):
        print(line)
    if "electrode_heights_ua" in result.sent:
        print(heights_line(result.sent["electrode_heights_ua"]))


def electrode_heights(result: Any) -> list[list[float]] | None:
    """Firmware v2: the heights (µA) each electrode was pulsed at over the study, in application order,
    from the timed replay (None without it).  On v2 every electrode has its own height, so one maximum
    for the session would hide an electrode held lower (or higher) than the rest."""
    per: list[set[float]] = [set() for _ in range(result.array.count)]
    seen = False
    for run in result.trials:
        d = run.delivered
        if d is None or "heights_ua" not in d["per_electrode"]:
            continue
        seen = True
        for i, hs in enumerate(d["per_electrode"]["heights_ua"]):
            per[i].update(hs)
    return [sorted(h) for h in per] if seen else None


def heights_line(heights: list[list[float]] | None) -> str:
    """The console's line for the per-electrode heights on v2 (electrodes grouped by equal heights)."""
    from .delivered import span

    if heights is None:
        return "firmware v2: per-electrode heights not known (no timed replay)"
    groups: dict[tuple[float, ...], list[int]] = {}
    for i, hs in enumerate(heights):
        if hs:
            groups.setdefault(tuple(hs), []).append(i)
    if not groups:
        return "firmware v2: no electrode was pulsed"
    parts = [
        f"{', '.join(f'{h:g}' for h in hs)} µA on electrode(s) {span(es)}"
        for hs, es in sorted(groups.items())
    ]
    return "firmware v2: heights delivered per electrode: " + "; ".join(parts)
