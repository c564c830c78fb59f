"""argparse types the subcommands share, and the check of their output paths. A bad value stops at parsing:
argparse prints the usage line and one sentence naming the option, and exits 2. An output path that cannot take
a file stops the command before it reads or computes anything (:func:`check_outputs`: one line, exit 2)."""

from __future__ import annotations

import argparse
import math
import os
from pathlib import Path
from typing import Literal, overload


def finite_float(text: str) -> float:
    """A number that is neither NaN nor infinite (every float option is a size, a noise or a time)."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"must be a finite number, got {text!r}")
    return value


def finite_or_inf(text: str) -> float:
    """A finite number or 'inf' (a bound that 'inf' turns off, such as --outlier-gate); NaN and -inf are refused."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None
    if not (math.isfinite(value) or value == math.inf):
        raise argparse.ArgumentTypeError(f"must be a finite number or inf, got {text!r}")
    return value


def path_argument(text: str) -> Path:
    """A path given on the command line; an empty one is refused (``Path("")`` would quietly mean the current
    folder)."""
    if not text:
        raise argparse.ArgumentTypeError("an empty path: name a file or folder")
    return Path(text)


def _integer(text: str) -> int:
    """``text`` as an integer; ArgumentTypeError (argparse's one sentence naming the option) when it is none."""
    try:
        return int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not an integer") from None


def random_seed(text: str) -> int:
    """A random seed: an integer >= 0 (numpy's generators take no negative seeds)."""
    value = _integer(text)
    if value < 0:
        raise argparse.ArgumentTypeError(f"a seed is an integer >= 0, got {value}")
    return value


def positive_int(text: str) -> int:
    """An integer >= 1."""
    value = _integer(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be >= 1, got {value}")
    return value


def bundle_metres(text: str) -> float:
    """A finite number of metres >= 0 (--bundle: the pose bundles' tolerance, mapping.bundling; 0: exact)."""
    from mapping.bundling import check_tolerance

    try:
        return check_tolerance(finite_float(text))
    except ValueError as exc:
        raise argparse.ArgumentTypeError(f"{exc} (0: every sample walks its rays)") from None


def positive_number(text: str) -> float:
    """A finite number > 0 (of the unit its option names)."""
    value = finite_float(text)
    if not value > 0:
        raise argparse.ArgumentTypeError(f"must be > 0, got {text!r}")
    return value


def positive_seconds(text: str) -> float:
    """A finite number of seconds > 0."""
    value = finite_float(text)
    if not value > 0:
        raise argparse.ArgumentTypeError(f"must be > 0 s, got {text!r}")
    return value


def pose_sample_count(text: str) -> int:
    """How many pose samples to take or publish per scan: 1 .. the most a PoseSamples message carries (every
    sample is ray-cast; a count past that stalls a mapper for minutes a scan)."""
    from schemas.messages import MAX_POSE_SAMPLES

    value = _integer(text)
    if not 1 <= value <= MAX_POSE_SAMPLES:
        raise argparse.ArgumentTypeError(f"must be in 1 .. {MAX_POSE_SAMPLES}, got {value}")
    return value


#: the largest odometry delay (s) --odom-delay accepts: a laser and odometry clock further apart is a wrong log
MAX_ODOM_DELAY = 5.0


def odom_delay_seconds(text: str) -> float:
    """--odom-delay in seconds: a finite number within +-MAX_ODOM_DELAY."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected seconds, got {text!r}") from None
    if not abs(value) <= MAX_ODOM_DELAY:
        raise argparse.ArgumentTypeError(f"expected a delay within +-{MAX_ODOM_DELAY:g} s, got {text}")
    return value


#: the longest no-return range (m) --no-return-range accepts; a scan's own range_max bounds it further
MAX_NO_RETURN_RANGE = 1e4


def no_return_metres(text: str) -> float:
    """--no-return-range in metres: a finite number (:func:`finite_float`) in [0, MAX_NO_RETURN_RANGE]."""
    value = finite_float(text)
    if not 0.0 <= value <= MAX_NO_RETURN_RANGE:
        raise argparse.ArgumentTypeError(f"expected metres in [0, {MAX_NO_RETURN_RANGE:g}], got {text}")
    return value


@overload
def checked_output(value: str | Path, option: str) -> Path: ...
@overload
def checked_output(value: None, option: str) -> None: ...
def checked_output(value: str | Path | None, option: str) -> Path | None:
    """The output path ``value`` given to ``option`` (None stays None), checked before any work is done: raise
    UsageError with one sentence naming the option, the path and what to do when
    :func:`schemas.files.write_atomically` could not write it (an empty path, a folder, a device, FIFO or socket,
    a missing or unwritable folder). Call it at the start of a command, before reading or computing anything."""
    from schemas.files import output_path_problem
    from services.errors import UsageError

    if value is None:
        return None
    problem = output_path_problem(value)
    if problem is not None:
        raise UsageError(f"{option} {os.fspath(value) or repr('')}: {problem}")
    return Path(value)


#: the files of an input folder that a command reads, which no output may replace: an MRCLAM folder's tables and a
#: ROS 2 bag's (and a simulator folder's, slam.simlog.SIMULATION_FILES)
INPUT_FOLDER_FILES = ("*.dat", "*.db3", "*.mcap", "metadata.yaml")


#: the kinds of file an output is (:func:`refuse_another_kind`)
OutputKind = Literal["map", "poses", "json"]

#: the first bytes of a file of each kind an output may replace: a zip archive (.npz: a map, or poses) and a JSON
#: object
KIND_HEADS = {"map": (b"PK\x03\x04", b"PK\x05\x06"), "poses": (b"PK\x03\x04", b"PK\x05\x06"), "json": (b"{",)}
#: the member a .npz archive of each kind holds (schemas.files: a map's logodds; a posed-scan or pose-distribution
#: file's stamps), which one of another kind does not: a truth raster, a map where poses go
KIND_MEMBERS = {"map": "logodds.npy", "poses": "stamps.npy"}
KIND_NAMES = {
    "map": "a map (.npz with logodds)",
    "poses": "a posed-scan or pose-distribution file (.npz with stamps)",
    "json": "a JSON object",
}


def refuse_another_kind(path: Path | None, kind: OutputKind, option: str) -> None:
    """UsageError when ``path`` holds a file that is not of ``kind`` (KIND_HEADS: "map", "poses" or "json"), which
    writing the output would replace: a new user's probe had `fuse -o keep.png` turn a PNG into a map,
    `calibrate -o map.npz` replace a map with JSON and `fuse -o sim/truth.npz` a truth raster with a map, exit 0.
    An empty file or archive, or none, is taken."""
    import zipfile

    from services.errors import UsageError

    if path is None or not path.is_file():
        return
    with path.open("rb") as file:
        head = file.read(64).lstrip()
    same = not head or head.startswith(KIND_HEADS[kind])
    if same and head and kind in KIND_MEMBERS:
        try:
            with zipfile.ZipFile(path) as archive:  # (its directory only: nothing is inflated)
                members = archive.namelist()
        except (zipfile.BadZipFile, OSError):
            members = None
        same = members is not None and (not members or KIND_MEMBERS[kind] in members)
    if not same:
        raise UsageError(
            f"{option} {path}: the file there is not {KIND_NAMES[kind]}, which this command writes, and would be "
            "replaced: remove it first, or give another path"
        )


def check_outputs(
    args: argparse.Namespace, inputs: tuple[Path, ...] = (), kinds: dict[str, OutputKind] | None = None, **options: str
) -> None:
    """Check every output path of ``args`` (its attribute name = the option that gives it, e.g. output="-o")
    with :func:`checked_output` and put the Path in its place. Output options take the text as given (no
    ``type=Path``, which would read an empty path as "."), so this must run before the command uses them.

    ``inputs``: what the command reads (files, or folders of :data:`INPUT_FOLDER_FILES` and the simulator's files);
    an output that is one of them, or one of such a folder's files, through links too, is refused: writing it would
    replace the data. ``kinds``: by attribute name, the kind of file the output is (:func:`refuse_another_kind`)."""
    from services.errors import UsageError
    from slam.simlog import SIMULATION_FILES

    read = {os.path.realpath(path) for path in inputs if path.is_file()}
    for folder in (path for path in inputs if path.is_dir()):
        patterns = (*INPUT_FOLDER_FILES, *SIMULATION_FILES)
        read |= {os.path.realpath(file) for pattern in patterns for file in folder.glob(pattern)}
    for name, option in options.items():
        path = checked_output(getattr(args, name), option)
        if path is not None and os.path.realpath(path) in read:
            raise UsageError(
                f"{option} {path}: is a file this command reads (its input); writing it would replace the data: "
                "give another path"
            )
        if kinds is not None and name in kinds:
            refuse_another_kind(path, kinds[name], option)
        setattr(args, name, path)
