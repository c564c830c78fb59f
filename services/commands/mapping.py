"""Subcommands on maps: fuse, export, eval."""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
from typing import TYPE_CHECKING

from services.commands.argtypes import (
    bundle_metres,
    check_outputs,
    finite_float,
    path_argument,
    pose_sample_count,
    random_seed,
)
from services.commands.options import add_choice, add_command, dest, option_argv

if TYPE_CHECKING:
    from mapping.adaptive import AdaptiveGrid, AdaptiveParams
    from mapping.grid import TiledGrid
    from services.fusion_runner import FusionOptions

#: --coarse-cell when not given, m
DEFAULT_COARSE_CELL = 0.8
#: the inverse sensor model's options and the mapping.sensor_model.SensorModel field each sets
SENSOR_MODEL_OPTIONS = {
    "--resolution": "resolution",
    "--sigma-model": "sigma",
    "--sigma0": "sigma0",
    "--sigma-slope": "sigma_slope",
    "--baseline-focal": "baseline_focal",
    "--peak-width": "peak_width",
}


def add_sensor_model_arguments(parser: argparse.ArgumentParser) -> None:
    """The inverse sensor model's options (shared with the mapper shards)."""
    group = parser.add_argument_group("inverse sensor model (docs/sensor_model.md)")
    group.add_argument("--resolution", type=finite_float, default=0.05, help="cell size in m (default 0.05)")
    add_choice(
        group,
        "--sigma-model",
        ("constant", "linear", "stereo"),
        "how range noise sigma grows with range z: constant sigma0, linear sigma0 + slope*z, "
        "or stereo z^2/(b*f) (default constant)",
    )
    group.add_argument(
        "--sigma0",
        type=finite_float,
        default=0.03,
        help="range noise sigma in m, or the linear model's intercept (default 0.03)",
    )
    group.add_argument(
        "--sigma-slope",
        type=finite_float,
        default=0.0,
        help="linear model: sigma grows by this many m per m (default 0: as constant)",
    )
    group.add_argument(
        "--baseline-focal",
        type=finite_float,
        default=0.0,
        help="stereo model: baseline (m) times focal length (px), so sigma = z^2/(b*f)",
    )
    group.add_argument(
        "--peak-width",
        type=finite_float,
        default=None,
        help="width l of the occupied peak in m (default: the cell diagonal)",
    )


def add_sampling_arguments(
    parser: argparse.ArgumentParser | argparse._ArgumentGroup,
    samples: str,
    accuracy: str,
    seed: str,
    seed_default: int | None = 0,
) -> None:
    """--mode, --samples, --accuracy and --seed: how the pose samples each scan is fused with are drawn
    (services.fusion_runner.PoseSampling); ``samples``, ``accuracy`` and ``seed`` are those options' help;
    ``seed_default`` None where a command refuses a --seed it would not read (its default is then 0)."""
    add_choice(parser, "--mode", ("mc", "ml"), "mc: all samples (default); ml: most likely")
    parser.add_argument("--samples", type=pose_sample_count, default=None, help=samples)
    parser.add_argument("--accuracy", type=finite_float, default=None, help=accuracy)
    parser.add_argument("--seed", type=random_seed, default=seed_default, help=seed)
    parser.add_argument(
        "--bundle",
        type=bundle_metres,
        default=0.0,
        metavar="METRES",
        help="mc only: walk the rays of a scan's pose samples in bundles, each from one sample that every other in it "
        "is within this tolerance of (|dp| + mean ray length x |dyaw|): fewer rays walked, every ray cast from a pose "
        "within that tolerance of its own (the geometric bound; the map's scores move by what it does to your poses: "
        "0.1 kept the office benchmark's map within 0.001 AUC and 1 %% Brier of the exact one, moved the README's "
        "EKF office run's AUC by 0.0075 and the warehouse's by 0.045; docs/performance.md, 'Bundled samples') "
        "(default 0: exact, every sample walks its rays)",
    )


def available_cores() -> int:
    """The cores this process may run on (os.sched_getaffinity; os.cpu_count where that is missing), at least 1."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # (not Linux)
        return os.cpu_count() or 1


def available_memory() -> int | None:
    """The memory this machine can give new processes without swapping (/proc/meminfo's MemAvailable), bytes; None
    where that cannot be read (not Linux)."""
    try:
        with open("/proc/meminfo", encoding="ascii") as meminfo:
            for line in meminfo:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    return None


def add_threads_argument(parser: argparse.ArgumentParser | argparse._ArgumentGroup, default: str) -> None:
    """--threads N: how many scans the fusion walks side by side, or parts of a lone scan's samples
    (mapping.fusion.FusionThreads); ``default`` says what it is when not given. Read with :func:`threads_from_args`."""
    parser.add_argument(
        "--threads",
        default=None,
        metavar="N",
        help="threads that fuse scans side by side, or a scan that comes alone in parts of its pose samples, each "
        "with a scratch window of its own (about 43 bytes a cell of a scan's window: 11 MB for a 12 m laser at "
        f"0.05 m); the map is the same bit for bit for any N (default: {default})",
    )


def threads_from_args(args: argparse.Namespace, default: int | None = None) -> int:
    """--threads as given, an integer >= 1, at most the cores this process may use (:func:`available_cores`; a
    larger count is lowered to them, with a note); when not given ``default``, or every core this process may use.
    UsageError (one sentence) for any other value."""
    from services.errors import UsageError

    if args.threads is None:
        return available_cores() if default is None else default
    try:
        threads = int(args.threads)
    except ValueError:
        threads = 0
    if threads < 1:
        raise UsageError(f"--threads must be a whole number of threads >= 1, got {args.threads!r}")
    cores = available_cores()
    if threads > cores:  # the map is the same for any count; more threads than cores only take more memory
        print(
            f"posegrid: note: --threads {threads} is more than the {cores} core(s) this process may use; fusing on "
            f"{cores} (more threads fuse no faster, and each takes a scratch window of its own)",
            file=sys.stderr,
            flush=True,
        )
        return cores
    return threads


def sensor_model_from_args(args: argparse.Namespace):
    """The sensor model the options describe; a sigma option that the chosen --sigma-model does not read is
    refused rather than ignored."""
    from mapping.sensor_model import SensorModel
    from schemas.files import RASTER_RESOLUTION_LIMITS
    from services.errors import UsageError

    unread = {"constant": ("sigma_slope", "baseline_focal"), "linear": ("baseline_focal",), "stereo": ("sigma_slope",)}[
        args.sigma_model
    ]
    for name in unread:
        if getattr(args, name) != 0.0:
            raise UsageError(
                f"--{name.replace('_', '-')} does nothing with --sigma-model {args.sigma_model}; drop it "
                "or choose the model that reads it"
            )
    low, high = RASTER_RESOLUTION_LIMITS  # a map of other cells could be written but never read back
    if not low <= args.resolution <= high:
        raise UsageError(f"--resolution must be in [{low:g}, {high:g}] m (a map file's cells), got {args.resolution:g}")

    return SensorModel(**{field: getattr(args, dest(option)) for option, field in SENSOR_MODEL_OPTIONS.items()})


def sensor_model_argv(args: argparse.Namespace) -> list[str]:
    """The sensor-model options of ``args`` as command-line arguments for another process (`posegrid run`'s
    shards)."""
    return option_argv(args, SENSOR_MODEL_OPTIONS)


def register(subparsers: argparse._SubParsersAction) -> None:
    _add_fuse(subparsers)
    _add_export(subparsers)
    evaluate = add_command(subparsers, "eval", run_eval)
    evaluate.add_argument("map", type=path_argument, help="map .npz")
    evaluate.add_argument("truth", type=path_argument, help="truth raster .npz")


def _add_fuse(subparsers: argparse._SubParsersAction) -> None:
    fuse = add_command(subparsers, "fuse", run_fuse)
    fuse.add_argument("posed", type=path_argument, help="posed-scan .npz (docs/formats.md)")
    fuse.add_argument(
        "-o",
        "--output",
        required=True,
        metavar="MAP.npz",
        help="map .npz to write (a regular file or a link to one; written in full or not at all)",
    )
    add_sampling_arguments(
        fuse,
        samples="pose samples drawn per scan for Gaussian poses (default: derived from the covariance and --accuracy)",
        accuracy="required accuracy in m of the Monte Carlo mean beam end point, for the derived sample "
        "count, at most 200 a scan (default: one cell)",
        seed="seed of the Gaussian pose sampling (default 0; mc with Gaussian poses only)",
        seed_default=None,
    )
    add_choice(
        fuse,
        "--grid",
        ("regular", "adaptive"),
        "regular: one cell size everywhere (default); adaptive: a quadtree that keeps fine cells "
        "only where the scans show structure (docs/adaptive.md); both write the same map file, the "
        "adaptive one with a 'level' layer",
    )
    add_threads_argument(fuse, "every core this process may use; --grid regular only")
    add_sensor_model_arguments(fuse)
    _add_adaptive_arguments(fuse)


def _add_adaptive_arguments(fuse: argparse.ArgumentParser) -> None:
    adaptive = fuse.add_argument_group("adaptive grid (--grid adaptive, docs/adaptive.md)")
    adaptive.add_argument(
        "--unknowns",
        action=argparse.BooleanOptionalAction,
        default=None,
        help="count unknowns (rays that ended before reaching a cell) in the split test, the "
        "paper's rule; --no-unknowns: only hits and misses, Einhorn et al.'s (default: unknowns)",
    )
    adaptive.add_argument(
        "--coarse-cell",
        type=finite_float,
        default=None,
        help="cell size in m where a scan first observes something: --resolution times a power "
        f"of two (default {DEFAULT_COARSE_CELL:g})",
    )
    adaptive.add_argument(
        "--significance",
        type=finite_float,
        default=None,
        help="significance of the chi-square split test; larger splits more (default 0.01)",
    )
    adaptive.add_argument(
        "--unknown-range",
        type=finite_float,
        default=None,
        metavar="M",
        help="count a ray's unknowns only up to M m beyond its return, or 3 sigma beyond it where its values end "
        "if that is farther (default: up to the range limit, the paper's rule). With a long-range laser among "
        "chairs and people, the shadow of every small object splits cells out to the range limit; 1.6 keeps the "
        "splits near the returns (docs/adaptive.md, real data)",
    )


def _add_export(subparsers: argparse._SubParsersAction) -> None:
    export = add_command(subparsers, "export", run_export)
    export.add_argument("map", type=path_argument, help="map .npz")
    export.add_argument(
        "--format",
        choices=("pgm", "png"),
        required=True,
        help="pgm: PATH.pgm and a map_server YAML beside it; png: an image for people",
    )
    export.add_argument("-o", "--output", required=True, metavar="IMAGE", help="image path (.pgm or .png)")
    add_choice(export, "--layer", ("probability", "variance"), "png only: which layer to draw (default probability)")
    export.add_argument(
        "--crop",
        type=finite_float,
        default=None,
        metavar="MARGIN",
        help="m: cut the map to its occupied cells plus MARGIN on every side (rays with no return "
        "clear space far beyond the walls; default: the whole map)",
    )


def _note_capped_samples(args: argparse.Namespace, posed) -> None:
    """Say so when --accuracy asks for more Gaussian pose samples than a scan takes (mapping.poses,
    DEFAULT_MAX_SAMPLES) on some scans: those are fused with that many, and their beam ends' Monte Carlo error is
    larger than asked (--accuracy 1e-6 and 0.001 gave the same map, without a word)."""
    from mapping.poses import DEFAULT_MAX_SAMPLES, samples_for_accuracy

    if args.mode != "mc" or args.accuracy is None or args.samples is not None or not posed.poses.is_gaussian:
        return  # (the default, one cell, takes the cap as docs/sensor_model.md says)
    accuracy = args.accuracy
    _, cov = posed.poses.gaussian()
    ranges = posed.range_max
    capped = sum(
        samples_for_accuracy(cov[t], float(ranges[t]), accuracy, DEFAULT_MAX_SAMPLES + 1) > DEFAULT_MAX_SAMPLES
        for t in range(len(cov))
    )
    if capped:
        print(
            f"posegrid fuse: note: --accuracy {accuracy:g} m asks for more than {DEFAULT_MAX_SAMPLES} pose samples on "
            f"{capped} of {len(cov)} scans; they are fused with {DEFAULT_MAX_SAMPLES}, so their beam ends' error is "
            f"larger than asked (--samples N draws N for every scan)",
            file=sys.stderr,
        )


def _note_peak_behind_returns(model, posed) -> None:
    """Say so when the sensor model puts its occupied peak more than half a cell behind the farthest return
    (r* - z = sigma^2 ln 2 / l, docs/sensor_model.md): the walls of the map then stand that far behind the
    surfaces the laser saw."""
    import numpy as np

    from mapping.sensor_model import TAIL_SIGMAS

    ranges = posed.ranges  # (each scan's own range limits; the NaN padding is not finite)
    hits = ranges[np.isfinite(ranges) & (ranges >= posed.range_min[:, None]) & (ranges <= posed.range_max[:, None])]
    if not hits.size:
        return
    z = float(hits.max())
    sigma = float(model.sigma_at(z))
    behind = min(float(model.peak_range(np.array([z]))[0]) - z, TAIL_SIGMAS * sigma)  # beams stop at z + 3 sigma
    if behind > model.resolution / 2:
        remedy = (
            "raise --peak-width towards sigma"
            if model.l < sigma  # the offset sigma^2 ln 2 / l is sigma ln 2 or more
            else f"cells of {model.resolution:.3g} m are far finer than the range noise: use cells nearer sigma "
            "(--resolution)"
        )
        print(
            f"posegrid fuse: note: at {z:.3g} m the range noise sigma is {sigma:.3g} m against a peak width l of "
            f"{model.l:.3g} m, so the strongest occupied evidence of a beam lies {behind:.3g} m behind its return, "
            f"and walls are drawn behind the surfaces; {remedy} (docs/sensor_model.md, section 1)",
            file=sys.stderr,
            flush=True,
        )


def _scans_without_beams(posed, model) -> int:
    """How many scans of ``posed`` have no beam the fusion uses: each reading below range_min, negative or -inf
    (mapping.beam_model.beam_table's skipped beams), so the scan adds nothing to the map."""
    from mapping.beam_model import BEAM_SKIP, beam_table

    return sum(
        not (beam_table(posed.scan_ranges(t), model, posed.range_min[t], posed.range_max[t]).kind != BEAM_SKIP).any()
        for t in range(len(posed.stamps))
    )


def _refuse_an_empty_map(args: argparse.Namespace, posed, empty_scans: int) -> None:
    """Raise UsageError naming ``args.posed`` when none of its scans has a usable beam: the map would be empty."""
    from services.errors import UsageError

    if empty_scans == len(posed.stamps):
        raise UsageError(
            f"{args.posed}: none of its {empty_scans} scans has a usable beam (every reading is below "
            f"range_min {posed.range_min.max():g} m, negative or -inf), so the map would be empty; nothing "
            f"written to {args.output}"
        )


def _refuse_a_map_too_wide(args: argparse.Namespace, posed, resolution: float) -> None:
    """UsageError before any fusion when the robot's positions alone span more tiles than one raster may hold
    (mapping.grid.MAX_RASTER_CELLS), which the map then does too (each scan observes the cells its rays start in).
    Found after every scan was fused, it cost a long run's whole time. A tile is taken off each side for the
    laser's offset and a sample's spread."""
    import numpy as np

    from mapping.grid import MAX_RASTER_CELLS, TILE_SIZE
    from services.errors import UsageError

    positions = posed.poses.mean[:, :2] if posed.poses.is_gaussian else posed.poses.samples[:, :, :2].reshape(-1, 2)
    tiles = np.floor(positions / (resolution * TILE_SIZE))
    span = np.maximum(tiles.max(axis=0) - tiles.min(axis=0) - 1, 0) * TILE_SIZE  # cells (x, y)
    if span[0] * span[1] > MAX_RASTER_CELLS:
        width, height = (span * resolution).tolist()
        raise UsageError(
            f"{args.posed}: the robot's positions alone span more than {width:.6g} m x {height:.6g} m, a map of "
            f"more than the {MAX_RASTER_CELLS} cells of {resolution:g} m one map file may hold; fuse it in parts "
            f"(a posed-scan file of each stretch of the run) or with a coarser --resolution; nothing fused"
        )


def _refuse_unread_options(args: argparse.Namespace) -> None:
    """UsageError for options `posegrid fuse` would not read: the adaptive grid's with --grid regular, the
    sample count's with --mode ml."""
    from services.errors import UsageError

    adaptive_options = {
        "--unknowns/--no-unknowns": args.unknowns,
        "--coarse-cell": args.coarse_cell,
        "--significance": args.significance,
        "--unknown-range": args.unknown_range,
    }
    given = [option for option, value in adaptive_options.items() if value is not None]
    if args.grid == "regular" and given:
        raise UsageError(f"{', '.join(given)} shape the adaptive grid only; add --grid adaptive or drop them")
    if args.grid == "adaptive" and args.threads is not None:
        raise UsageError("--threads fuses the regular grid's scans side by side; the adaptive grid fuses on one thread")
    if args.grid == "adaptive" and args.bundle > 0:
        raise UsageError("--bundle walks the regular grid's rays in bundles; the adaptive grid walks every sample's")
    if args.mode == "ml" and (args.samples is not None or args.accuracy is not None or args.seed is not None):
        raise UsageError(
            "--samples, --accuracy and --seed set how mc draws Gaussian pose samples; ml uses the mean pose only"
        )
    refuse_bundle_with_ml(args)


def refuse_bundle_with_ml(args: argparse.Namespace) -> None:
    """--bundle (add_sampling_arguments) bundles the samples mc walks; with --mode ml it would do nothing, so it is
    refused (UsageError), here and for the mapper and `run`."""
    from services.errors import UsageError

    if args.mode == "ml" and args.bundle > 0:
        raise UsageError("--bundle bundles the pose samples mc walks; ml walks the mean pose only")


def _adaptive_params(args: argparse.Namespace) -> AdaptiveParams:
    """The mapping.adaptive.AdaptiveParams of the adaptive-grid options (theirs where left unset)."""
    from mapping.adaptive import AdaptiveParams, level_for_cell_size
    from mapping.errors import InputError
    from mapping.grid import TILE_SIZE
    from services.errors import UsageError

    defaults = AdaptiveParams()
    unknowns = defaults.unknowns if args.unknowns is None else args.unknowns
    if args.unknown_range is not None and not unknowns:
        raise UsageError("--unknown-range limits the unknowns that --no-unknowns turns off; drop one of them")
    coarse_cell = args.coarse_cell if args.coarse_cell is not None else DEFAULT_COARSE_CELL
    given = "--coarse-cell" if args.coarse_cell is not None else "--coarse-cell (default)"
    levels = int(TILE_SIZE).bit_length() - 1  # (the coarsest cell is a whole tile of the adaptive grid)
    largest = args.resolution * (1 << levels)
    try:
        start_level = level_for_cell_size(coarse_cell, args.resolution)
    except InputError:
        raise UsageError(
            f"{given} {coarse_cell:g} m must be --resolution {args.resolution:g} m times a power of two, at most "
            f"{largest:g} m (a tile of {TILE_SIZE} cells); give one, or another --resolution"
        ) from None
    if start_level > levels:
        raise UsageError(
            f"{given} {coarse_cell:g} m is coarser than a tile: at most {largest:g} m at --resolution "
            f"{args.resolution:g} m (tiles of {TILE_SIZE} cells)"
        )
    return AdaptiveParams(
        start_level=start_level,
        unknowns=unknowns,
        significance=defaults.significance if args.significance is None else args.significance,
        unknown_range=args.unknown_range,
    )


def run_fuse(args: argparse.Namespace) -> int:
    """fuse a posed-scan file into an occupancy map

    Build an occupancy map from a posed-scan file (scans + per-scan pose distributions). mode mc integrates every
    pose sample (Monte Carlo, the paper's method) and keeps a variance layer that shows where pose uncertainty
    blurred the map; mode ml uses the most likely pose only."""
    from schemas.files import MapFile, load_posed_scans, save_map
    from services.errors import UsageError

    check_outputs(args, inputs=(args.posed,), kinds={"output": "map"}, output="-o")
    _refuse_unread_options(args)
    threads = threads_from_args(args)
    model = sensor_model_from_args(args)
    posed = load_posed_scans(args.posed)
    empty_scans = _scans_without_beams(posed, model)
    _refuse_an_empty_map(args, posed, empty_scans)
    _refuse_a_map_too_wide(args, posed, model.resolution)
    _note_peak_behind_returns(model, posed)
    if not posed.poses.is_gaussian and (args.samples is not None or args.accuracy is not None or args.seed is not None):
        raise UsageError(
            f"{args.posed} holds pose samples, which are fused as they are; --samples, --accuracy and --seed "
            "set how to draw from Gaussian poses"
        )
    _note_capped_samples(args, posed)
    options: FusionOptions = {
        "mode": args.mode,
        "model": model,
        "n_samples": args.samples,
        "seed": 0 if args.seed is None else args.seed,
        "accuracy": args.accuracy,
        "progress": True,
        "bundle": args.bundle,
    }
    grid: AdaptiveGrid | TiledGrid
    if args.grid == "adaptive":
        from services.fusion_runner import fuse_posed_scans_adaptive

        params = _adaptive_params(args)
        grid = fuse_posed_scans_adaptive(posed, params=params, **options)
        summary = f"{grid.active_cells} active cells ({'with' if params.unknowns else 'without'} unknowns)"
    else:
        from services.fusion_runner import fuse_posed_scans

        options["threads"] = threads
        grid = fuse_posed_scans(posed, **options)
        summary = None
    from mapping.grid import RasterTooLarge

    try:
        raster = grid.rasterize()
    except RasterTooLarge as exc:  # (the check before the fusion sees the robot's positions only, not its rays)
        raise UsageError(
            f"{args.posed}: {exc}: fuse it in parts (a posed-scan file of each stretch of the run) or with a coarser "
            f"--resolution; nothing written to {args.output}"
        ) from None
    if not raster["observed"].any():
        raise UsageError(
            f"{args.posed}: its scans observed no cell, so the map is empty; nothing written to {args.output}"
        )
    summary = summary or f"{int(raster['observed'].sum())} observed"
    save_map(args.output, MapFile.from_raster(raster))
    height, width = raster["logodds"].shape
    unusable = f", {empty_scans} without a usable beam (every reading below range_min, negative or -inf)"
    print(
        f"wrote {args.output}: {width} x {height} cells at {args.resolution} m, {summary}, "
        f"{len(posed.stamps) - empty_scans} scans fused ({args.mode}){unusable if empty_scans else ''}"
    )
    return 0


def run_export(args: argparse.Namespace) -> int:
    """export a map as PGM+YAML (ROS map_server) or PNG

    Export a map file. pgm writes PATH (.pgm) and a map_server YAML beside it; png writes an image for people
    (grey level 1 - p: free light, occupied black; unobserved pale blue), or the variance layer with --layer
    variance."""
    from mapping.export import crop_to_occupied, render_pgm, render_png
    from schemas.files import load_map, write_atomically, written_together
    from services.errors import UsageError

    check_outputs(args, inputs=(args.map,), output="-o")
    if args.output.suffix.lower() != f".{args.format}":
        raise UsageError(
            f"-o {args.output}: a {args.format} export needs a name ending in .{args.format}"
            + (" (the map_server YAML is written beside it as NAME.yaml)" if args.format == "pgm" else "")
        )
    if args.format == "pgm" and args.layer != "probability":
        raise UsageError("--layer variance draws a png; a pgm for map_server holds the occupancy only")
    yaml_path = None  # set for a pgm only
    if args.format == "pgm":  # the YAML must not replace the map either (a map file named NAME.yaml)
        args.map_server_yaml = args.output.with_suffix(".yaml")
        check_outputs(args, inputs=(args.map,), map_server_yaml="the map_server YAML beside -o,")
        yaml_path = args.map_server_yaml
    map_file = load_map(args.map)
    arrays = vars(map_file)
    if args.crop is not None:
        arrays = crop_to_occupied(arrays, args.crop)
    if yaml_path is not None:  # a pgm
        pgm, yaml = render_pgm(arrays, image_name=args.output.name)
        with written_together():  # (an image beside another map's YAML would load at the wrong scale)
            write_atomically(args.output, lambda handle: handle.write(pgm))
            write_atomically(yaml_path, lambda handle: handle.write(yaml.encode()))
        print(f"wrote {args.output} and {yaml_path}")
    else:
        png = render_png(arrays, layer=args.layer)
        write_atomically(args.output, lambda handle: handle.write(png))
        print(f"wrote {args.output} ({args.layer})")
    return 0


def run_eval(args: argparse.Namespace) -> int:
    """score a map against a truth raster (AUC, Brier, NLL)

    Score MAP against TRUTH over the truth's visible cells; prints one JSON line with auc (null when those cells
    hold one class only), brier, nll (natural log, per cell, the probabilities clipped to [1e-6, 1 - 1e-6] so that a
    certain mistake costs ln 1e6), n (cells scored) and informed (those of them observed map cells cover, in part or
    whole). Each truth cell takes the map's probability averaged over its area; parts the map does not cover
    or has not observed count as 0.5, so the two rasters may differ in origin, extent and resolution. A map that
    observed none of the scored cells gets a warning: its AUC of 0.5 says only that the two do not overlap."""
    from mapping.evaluation import score_map
    from schemas.files import load_map, load_truth

    scores = score_map(vars(load_map(args.map)), vars(load_truth(args.truth)))
    report: dict[str, float | None] = dict(scores)
    if math.isnan(scores["auc"]):  # one class only: Brier and NLL still say something, AUC nothing
        print(
            f"posegrid eval: the truth's {scores['n']} visible cells hold one class only, so the ROC AUC is undefined "
            "(null)",
            file=sys.stderr,
        )
        report["auc"] = None
    if scores["informed"] == 0:
        print(
            f"posegrid eval: warning: the map has observed none of the truth's {scores['n']} visible cells, so these "
            "scores are those of a map of 0.5 everywhere; check that the map and the truth share a frame and overlap "
            "(their origins and extents)",
            file=sys.stderr,
        )
    print(json.dumps(report, allow_nan=False))  # the rest is finite: the map and the truth are validated
    return 0
