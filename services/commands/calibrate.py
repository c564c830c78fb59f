"""`posegrid calibrate`: fit a robot's calibration (slam.calibration) to its own data, without ground truth, and
write it as a calibration file that `posegrid slam`, `slam-node` and `run` read (--calibration FILE).

Units: metres, radians, seconds (every field of the file names its unit; docs/slam.md, "Calibration").
"""

from __future__ import annotations

import argparse
import time

from services.commands.argtypes import check_outputs, finite_float, path_argument
from services.commands.options import add_command
from services.commands.slam import add_drive_angle_sd_option, add_heading_frame_option, add_mrclam_input_options

#: --fraction's default: the whole input
DEFAULT_FRACTION = 1.0


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = add_command(subparsers, "calibrate", run_calibrate)
    parser.add_argument("input", type=path_argument, help="MRCLAM folder (with --robot) or simulator folder")
    parser.add_argument("-o", "--output", required=True, metavar="CALIBRATION.json", help="calibration file to write")
    add_mrclam_input_options(parser, "take a step")
    add_heading_frame_option(parser, "the fit")
    parser.add_argument(
        "--fraction",
        type=finite_float,
        default=DEFAULT_FRACTION,
        help="fit on the first FRACTION of the input's time span, in (0, 1] (default 1: all of it); e.g. 0.5 to "
        "score the calibration on the half it was not fitted to",
    )
    add_drive_angle_sd_option(parser, "state ", "the fit's: half the angle by which drive and camera disagree")


def _first_part(sequence, fraction: float):
    """The steps of ``sequence`` within the first ``fraction`` of its time span."""
    from dataclasses import replace

    import numpy as np

    stamps = sequence.stamps
    until = stamps[0] + fraction * (stamps[-1] - stamps[0])
    steps = int(np.searchsorted(stamps, until, side="right"))
    controls, measurements = sequence.control_ptr[steps], sequence.measurement_ptr[steps]
    return replace(
        sequence,
        stamps=stamps[:steps],
        controls=sequence.controls[:controls],
        control_ptr=sequence.control_ptr[: steps + 1],
        measurements=sequence.measurements[:measurements],
        landmark_ids=sequence.landmark_ids[:measurements],
        measurement_ptr=sequence.measurement_ptr[: steps + 1],
    )


def run_calibrate(args: argparse.Namespace) -> int:
    """fit a robot's calibration to its data alone and write it as a calibration file

    Estimate, from INPUT alone (no ground truth), what the landmark filters need to know about the robot: the delay
    of its velocity commands, the scale of its speeds and its yaw-rate bias, its camera's range calibration and
    bearing bias, and the noise of its motion and of its landmark measurements (slam.selfcal: the filters' own
    estimate of the trajectory and the map stands in for ground truth, over several rounds). Two things cannot be
    had from the data: the map's overall scale (the ranges set it), and whether the angle by which the drive and the
    camera disagree is the camera's or the drive's (a crab): --heading-frame says, or the fit gives half to each and
    states the drive angle's sd as the half (--drive-angle-sd states another). Writes a JSON calibration file for
    `posegrid slam`, `slam-node` and `run` (--calibration FILE) and prints what it found."""
    from dataclasses import replace

    from schemas.files import write_atomically
    from services.commands.slam import landmark_input_kind, mrclam_input, sim_folder_input, stated_drive_angle_sd
    from services.errors import UsageError
    from slam.calibration import calibration_text
    from slam.selfcal import DELAY_GRID, NotEnoughData, UndeterminedParameter, self_calibrate

    check_outputs(args, inputs=(args.input,), kinds={"output": "json"}, output="-o")
    if not 0.0 < args.fraction <= 1.0:
        raise UsageError(f"--fraction must be in (0, 1], got {args.fraction:g}")
    stated_drive_angle_sd(args, 0.0)  # a bad --drive-angle-sd is refused before the fit
    delays: tuple[float, ...]
    if landmark_input_kind(args.input) == "sim":
        log = sim_folder_input(args)
        sequence_at, delays, what = (lambda delay: log.sequence()), (0.0,), f"{args.input}"
    else:
        _, sequence_at, _ = mrclam_input(args)
        delays, what = DELAY_GRID, f"{args.input} robot {args.robot}"
    started = time.perf_counter()
    try:
        fit = self_calibrate(
            lambda delay: _first_part(sequence_at(delay), args.fraction),
            delays=delays,
            source=f"posegrid calibrate {what}, first {args.fraction:g} of its time span",
            heading_frame=args.heading_frame or "unknown",
        )
    except UndeterminedParameter as exc:
        raise UsageError(f"{what}: cannot calibrate from it: {exc}") from None
    except NotEnoughData as exc:
        raise UsageError(f"{what}: too little to calibrate from: {exc}") from None
    calibration = replace(fit.calibration, drive_angle_sd=stated_drive_angle_sd(args, fit.calibration.drive_angle_sd))
    text = calibration_text(calibration, args.output).encode()
    write_atomically(args.output, lambda handle: handle.write(text))
    print(f"wrote {args.output} in {time.perf_counter() - started:.1f} s: {calibration.summary()}")
    return 0
