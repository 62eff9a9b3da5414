"""``tactdeform-hw export``: a TactDeform frames record → an eTactileKit pattern file.

``tactdeform-hw render --frames FRAMES.jsonl`` records what the renderer sent, frame by frame.  This
command turns that record into a pattern file the eTactileKit GUI (and ``tactdeform-hw play``) can play:
each sent frame becomes a step held until the next one (the last to the end of the record plus one frame
interval, unless ``--last-ms`` says otherwise), identical consecutive frames merge, and delays are whole
milliseconds rounded on the cumulative time line.  ``--array-out`` also writes the electrode
array as an eTactileKit array file, so the GUI draws the pattern on the right layout.
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from ..errors import ConfigurationError
from .common import print_json, progress
from .options import add_finisher, add_frequency, add_option, duration, polarity_code, range_check


def register(sub: Any) -> None:
    p: argparse.ArgumentParser = sub.add_parser(
        "export",
        help="turn a frames record (render --frames) into an eTactileKit pattern file",
        description="Convert a TactDeform frames record (JSON lines with t, electrodes, sent, …) into an "
        "eTactileKit pattern file (Pattern_Data) that the eTactileKit GUI and 'tactdeform-hw play' can play. "
        "Only frames that were sent become steps (the board keeps the last pattern it was sent); identical "
        "consecutive frames merge into one step.",
    )
    p.add_argument("frames", help="frames record written by 'tactdeform-hw render --frames'")
    p.add_argument("-o", "--out", required=True, help="pattern file to write (.json)")
    add_frequency(p, help="params.frequency in Hz for every step (default 125)")
    add_finisher(p, range_check("frequency", "--frequency-hz", 1, 65535, "Hz"))
    add_option(
        p,
        "--polarity",
        old=("--stim-mode",),
        old_type=int,
        old_choices=(0, 1),
        dest="stim_mode",
        type=polarity_code,
        default=1,
        metavar="{anodic,cathodic}",
        old_note="--stim-mode 1 is --polarity anodic, 0 is cathodic",
        help="the polarity the GUI sends, written as params.stim_mode (anodic = 1, cathodic = 0): "
        "anodic (default, TactDeform) or cathodic",
    )
    p.add_argument(
        "--last-ms",
        type=duration("ms"),
        help="how long the last step lasts (default: to the end of the record plus one frame interval, "
        "the median time between frames)",
    )
    p.add_argument("--all-frames", action="store_true", help="also export frames that were not sent")
    p.add_argument(
        "--no-merge", action="store_true", help="keep identical consecutive frames as separate steps"
    )
    p.add_argument(
        "--array",
        metavar="ARRAY.json",
        help="eTactileKit array file the frames were rendered for (default: the TactDeform 32-electrode pad)",
    )
    p.add_argument(
        "--array-out",
        metavar="ARRAY.json",
        help="also write the electrode array as an eTactileKit array file",
    )
    p.add_argument(
        "--gif",
        metavar="OUT.gif",
        help="also draw the exported steps as an animated GIF (needs the plot extra)",
    )
    p.add_argument("--json", action="store_true", help="print a JSON summary on stdout")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from ..formats import (
        read_array_file,
        read_frames_file,
        sequence_from_frames,
        write_array_file,
        write_pattern_file,
    )
    from ..render.array import ElectrodeArray

    frames = read_frames_file(args.frames)
    if args.last_ms is not None and not args.last_ms >= 0:
        raise ConfigurationError(f"--last-ms={args.last_ms!r} is out of range: a non-negative number of ms")
    seq = sequence_from_frames(
        frames,
        frequency_hz=args.frequency,
        stim_mode=args.stim_mode,
        last_ms=args.last_ms,
        merge=not args.no_merge,
        sent_only=not args.all_frames,
    )
    array_file = read_array_file(args.array) if args.array else None
    array = array_file.array if array_file is not None else ElectrodeArray.tactdeform()
    if seq.electrodes != len(array.positions_mm):
        raise ConfigurationError(
            f"{Path(args.frames).name}: frames have {seq.electrodes} electrode level(s) but the array "
            f"{array.name} has {len(array.positions_mm)}; pass --array with the array they were rendered for"
        )
    seq = type(seq)(seq.steps, extra=seq.extra, source=Path(args.out).name)
    out = write_pattern_file(seq, args.out)
    summary: dict[str, Any] = {
        "frames": len(frames),
        "steps": len(seq.steps),
        "electrodes": seq.electrodes,
        "duration_ms": seq.duration_ms,
        "frequency_hz": args.frequency,
        "stim_mode": args.stim_mode,
        "pattern_file": str(out),
    }
    if args.array_out:
        outline = array_file.outline_mm if array_file is not None else None
        board = array_file.board if array_file is not None else None
        summary["array_file"] = str(write_array_file(array, args.array_out, outline, board))
    if args.gif:
        from ..viz.array_picture import draw_array_gif, frames_from_sequence

        info = draw_array_gif(
            array,
            frames_from_sequence(seq),
            args.gif,
            outline_mm=array_file.outline_mm if array_file is not None else None,
            title=f"{Path(args.frames).name} → {out.name}",
        )
        for note in info.notes:
            progress(f"note: {note}")
        summary["gif"] = {"path": str(info.path), "frames": info.frames, "size_px": list(info.size_px)}
    if args.json:
        print_json(summary)
    else:
        print(
            f"wrote {out}: {len(seq.steps)} step(s) from {len(frames)} frame(s), "
            f"{seq.duration_ms / 1000:.3f} s, {seq.electrodes} electrodes, {args.frequency} Hz, stim_mode "
            f"{args.stim_mode}"
        )
    return 0
