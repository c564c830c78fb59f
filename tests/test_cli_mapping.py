"""`posegrid fuse / export / eval` as a user runs them: the console script's main() on real files, its exit code and
what it prints; one test runs them as real processes too."""

from __future__ import annotations

import contextlib
import io
import json
import os
import subprocess
import sys
import time
import warnings
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

from schemas.errors import FormatError
from schemas.files import (
    PoseDistributionFile,
    PoseSet,
    TruthRaster,
    load_map,
    save_pose_distribution,
    save_posed_scans,
    save_truth,
    write_atomically,
)
from services.cli import main
from worlds import room_posed_scans

ROOT = Path(__file__).resolve().parents[1]


def posegrid(*args: str) -> subprocess.CompletedProcess:
    """`posegrid ARGS` through main() in this process: the code the console script runs (``sys.exit(main())``), its
    exit code (argparse's SystemExit included) and what it printed, without a new interpreter's start (0.8 CPU s,
    about 70 runs in this file). An exception main() lets out fails the test, as its traceback would fail a user; a
    Python warning goes to stderr, where a process would print it (not to pytest's summary)."""
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err), warnings.catch_warnings(record=True) as seen:
        warnings.simplefilter("always")
        try:
            code = main(list(args))
        except SystemExit as exc:  # argparse: --help, usage errors
            code = exc.code if isinstance(exc.code, int) else int(exc.code is not None)
    for warning in seen:
        err.write(warnings.formatwarning(warning.message, warning.category, warning.filename, warning.lineno))
    return subprocess.CompletedProcess(["posegrid", *args], code, out.getvalue(), err.getvalue())


def posegrid_process(*args: str, preexec_fn: Callable[[], None] | None = None) -> subprocess.CompletedProcess:
    """`posegrid ARGS` as a process of its own, as from a shell (``preexec_fn``: run in the child before it starts,
    to set its limits)."""
    return subprocess.run(
        [sys.executable, "-m", "services.cli", *args],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=300,
        check=False,
        preexec_fn=preexec_fn,
    )


@pytest.fixture(scope="module")
def posed_file(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("posed") / "room.npz"
    save_posed_scans(path, room_posed_scans(steps=10, beams=120))
    return path


def test_fuse_says_when_the_sensor_model_draws_walls_behind_the_returns(posed_file, tmp_path):
    """sigma^2 ln 2 / l behind the return: 0.009 m with the defaults (no note); with a stereo sigma of 0.18 m at 3 m
    (b f = 50) against l = 0.071 m, about 0.3 m, six cells, which the map would show without a word."""
    quiet = posegrid("fuse", str(posed_file), "-o", str(tmp_path / "a.npz"))
    assert quiet.returncode == 0 and "behind the return" not in quiet.stderr, quiet.stderr
    noisy = posegrid(
        "fuse", str(posed_file), "-o", str(tmp_path / "b.npz"), "--sigma-model", "stereo", "--baseline-focal", "50"
    )
    assert noisy.returncode == 0 and "behind its return" in noisy.stderr and "--peak-width" in noisy.stderr
    # l already wider than sigma (1 m against 0.03): the offset (0.6 mm) shows only in cells finer than it, and the
    # remedy is coarser cells, not a peak width "raised towards sigma"
    fine = posegrid("fuse", str(posed_file), "-o", str(tmp_path / "c.npz"), "--resolution", "1e-4", "--peak-width", "1")
    assert "behind its return" in fine.stderr and "--resolution" in fine.stderr and "towards sigma" not in fine.stderr


def test_fuse_says_when_the_accuracy_asked_passes_the_sample_cap(posed_file, tmp_path):
    """A new user's probe: --accuracy 1e-6 and 0.001 gave the same map byte for byte (the scans' sample counts are
    capped at 200) without a word. A micrometre asks for more than 200 on every scan with any spread; 10 m on
    none."""
    fine = posegrid("fuse", str(posed_file), "-o", str(tmp_path / "a.npz"), "--accuracy", "1e-6")
    assert fine.returncode == 0 and "asks for more than 200 pose samples on" in fine.stderr, fine.stderr
    assert "of 10 scans; they are fused with 200" in fine.stderr
    coarse = posegrid("fuse", str(posed_file), "-o", str(tmp_path / "b.npz"), "--accuracy", "10")
    assert coarse.returncode == 0 and "pose samples on" not in coarse.stderr, coarse.stderr


def test_fuse_says_why_a_scan_is_slow_and_only_then(posed_file, tmp_path, capsys, monkeypatch):
    """A new user's probe: with a cold kernel cache `posegrid fuse` printed nothing for 65 s (its bar is off
    without a terminal). A scan slower than SLOW_SCAN (here the third, as a kernel its poses first need compiles)
    says, once, that the kernels are compiling; fast ones say nothing."""
    import services.fusion_runner as runner

    assert main(["fuse", str(posed_file), "-o", str(tmp_path / "fast.npz")]) == 0
    assert "kernels are compiling" not in capsys.readouterr().err  # (warm: a scan takes ms)
    calls = [0]
    pass_for = runner._pass_for

    def slow_third(*args):
        calls[0] += 1
        if calls[0] in (3, 5):
            time.sleep(1.0)  # (as a compile)
        return pass_for(*args)

    monkeypatch.setattr(runner, "_pass_for", slow_third)
    monkeypatch.setattr(runner, "SLOW_SCAN", 0.2)
    assert main(["fuse", str(posed_file), "-o", str(tmp_path / "slow.npz")]) == 0
    assert capsys.readouterr().err.count(runner.SLOW_SCAN_NOTE) == 1


def test_fuse_is_reproducible_byte_for_byte(posed_file, tmp_path):
    outputs = []
    for name in ("a.npz", "b.npz"):
        result = posegrid("fuse", str(posed_file), "-o", str(tmp_path / name), "--samples", "20", "--seed", "5")
        assert result.returncode == 0, result.stderr
        outputs.append((tmp_path / name).read_bytes())
    assert outputs[0] == outputs[1]
    other = posegrid("fuse", str(posed_file), "-o", str(tmp_path / "c.npz"), "--samples", "20", "--seed", "6")
    assert other.returncode == 0 and (tmp_path / "c.npz").read_bytes() != outputs[0]


def test_fuse_export_eval_round_trip(posed_file, tmp_path):
    map_path = tmp_path / "map.npz"
    assert posegrid("fuse", str(posed_file), "-o", str(map_path)).returncode == 0
    room = load_map(map_path)
    # the 4 m x 3 m room (80 x 60 cells) is seen; the raster is cropped to observed cells, which reach
    # z + 3 sigma (0.09 m) past the walls plus the pose spread: at most 0.2 m on each side
    height, width = room.logodds.shape
    assert 80 <= width <= 88 and 60 <= height <= 68
    assert room.variance is not None and room.variance.max() > 0
    # export
    assert posegrid("export", str(map_path), "--format", "pgm", "-o", str(tmp_path / "m.pgm")).returncode == 0
    assert (tmp_path / "m.pgm").read_bytes().startswith(f"P5\n{width} {height}\n255\n".encode())
    assert 'image: "m.pgm"' in (tmp_path / "m.yaml").read_text()
    for layer in ("probability", "variance"):
        result = posegrid(
            "export", str(map_path), "--format", "png", "-o", str(tmp_path / f"{layer}.png"), "--layer", layer
        )
        assert result.returncode == 0, result.stderr
    # eval against the room's truth: walls are the border cells of the box
    truth = np.zeros((60, 80), bool)
    truth[[0, -1], :] = True
    truth[:, [0, -1]] = True
    save_truth(tmp_path / "truth.npz", TruthRaster(truth, np.ones_like(truth), np.zeros(2), 0.05))
    result = posegrid("eval", str(map_path), str(tmp_path / "truth.npz"))
    scores = json.loads(result.stdout)
    assert scores["n"] == 4800 and scores["auc"] > 0.95 and scores["brier"] < 0.1


def _bad(tmp_path: Path, name: str, **arrays) -> Path:
    path = tmp_path / name
    np.savez(path, **arrays)
    return path


def good_arrays(**override):
    arrays = dict(
        ranges=np.ones((2, 3), np.float32),
        angle_min=0.0,
        angle_increment=0.1,
        range_min=0.1,
        range_max=5.0,
        stamps=np.arange(2.0),
        samples=np.zeros((2, 1, 3)),
        weights=np.ones((2, 1)),
    )
    arrays.update(override)
    return {k: v for k, v in arrays.items() if v is not None}


@pytest.mark.parametrize(
    "arrays, phrase",
    [
        (good_arrays(weights=np.full((2, 1), 0.5)), "sum to"),
        (good_arrays(samples=np.full((2, 1, 3), np.nan)), "NaN"),
        (good_arrays(ranges=np.ones(3, np.float32)), "shape (T, B)"),
        (good_arrays(stamps=None), "missing key 'stamps'"),
        (good_arrays(samples=np.zeros((2, 1, 2))), "'samples' must have shape"),
        (good_arrays(range_max=0.05), "range_min < range_max"),
        (
            good_arrays(
                ranges=np.ones((0, 3), np.float32),
                stamps=np.zeros(0),
                samples=np.zeros((0, 1, 3)),
                weights=np.zeros((0, 1)),
            ),
            "holds no steps",
        ),
        (good_arrays(ranges=np.ones((2, 3), np.complex64)), "must hold real numbers"),
        (good_arrays(samples=np.full((2, 1, 3), "x")), "must hold real numbers"),
        (good_arrays(angle_min=1e30), "'angle_min' = 1e+30 rad is more than a full turn"),
        (good_arrays(ranges=np.ones((2, 70), np.float32)), "70 beams 0.1 rad apart sweep 6.9 rad, more than a full"),
        (good_arrays(stamps=np.arange(2.0, dtype=np.float32)), "'stamps' must be float64 seconds, got float32"),
    ],
)
def test_malformed_posed_files_exit_2_with_one_line(tmp_path, arrays, phrase):
    result = posegrid("fuse", str(_bad(tmp_path, "bad.npz", **arrays)), "-o", str(tmp_path / "m.npz"))
    assert result.returncode == 2
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and phrase in lines[0] and "Traceback" not in result.stderr


@pytest.mark.parametrize("run", [posegrid, posegrid_process], ids=["main", "process"])
def test_not_an_npz_and_missing_file(tmp_path, run):
    junk = tmp_path / "junk.npz"
    junk.write_text("hello")
    fifo = tmp_path / "fifo.npz"
    os.mkfifo(fifo)
    for path, phrase in (
        (junk, "not a .npz archive"),
        (tmp_path / "absent.npz", "no such file"),
        (tmp_path, "is a folder"),  # these three were "no such file"
        (fifo, "is a FIFO"),
        (Path("/dev/null"), "is a character device"),
    ):
        result = run("fuse", str(path), "-o", str(tmp_path / "m.npz"))
        assert result.returncode == 2 and len(result.stderr.strip().splitlines()) == 1 and phrase in result.stderr


def test_fuse_then_export_as_processes(posed_file, tmp_path):
    """Both commands as processes of their own, as from a shell: exit 0, and export reads what fuse wrote."""
    fused, exported = tmp_path / "map.npz", tmp_path / "map.pgm"
    assert posegrid_process("fuse", str(posed_file), "-o", str(fused)).returncode == 0
    assert posegrid_process("export", str(fused), "-o", str(exported), "--format", "pgm").returncode == 0
    assert exported.read_bytes().startswith(b"P5")


def test_bad_option_value_exit_2(posed_file, tmp_path):
    result = posegrid("fuse", str(posed_file), "-o", str(tmp_path / "m.npz"), "--sigma0", "-1")
    assert result.returncode == 2 and "sigma0" in result.stderr
    # cells no map file may hold: fuse wrote a map of 2 km cells that export and eval then refused
    for resolution in ("2000", "5e-7"):
        result = posegrid("fuse", str(posed_file), "-o", str(tmp_path / "m.npz"), "--resolution", resolution)
        _one_line_exit_2(result, "--resolution must be in [1e-06, 1000] m")
    assert not (tmp_path / "m.npz").exists()


@pytest.mark.parametrize(
    "options, phrase",
    [
        (["--mode", "ml", "--samples", "20"], "ml uses the mean pose only"),
        (["--mode", "ml", "--seed", "7"], "ml uses the mean pose only"),  # (was taken, and changed nothing)
        (["--sigma-slope", "0.01"], "--sigma-slope does nothing with --sigma-model constant"),
        (
            ["--sigma-model", "linear", "--baseline-focal", "300"],
            "--baseline-focal does nothing with --sigma-model linear",
        ),
    ],
)
def test_options_the_fusion_would_ignore_are_refused(posed_file, tmp_path, options, phrase):
    _one_line_exit_2(posegrid("fuse", str(posed_file), "-o", str(tmp_path / "m.npz"), *options), phrase)
    assert not (tmp_path / "m.npz").exists()


def _one_line_exit_2(result: subprocess.CompletedProcess, phrase: str) -> None:
    lines = result.stderr.strip().splitlines()
    assert result.returncode == 2 and len(lines) == 1 and phrase in lines[0] and "Traceback" not in result.stderr, (
        result.stderr
    )


def test_an_npy_or_a_damaged_archive_is_one_line(tmp_path):
    bare = tmp_path / "bare.npz"
    with open(bare, "wb") as handle:  # np.save on a handle keeps the name: a .npy under a .npz name
        np.save(handle, np.zeros(3))
    _one_line_exit_2(posegrid("fuse", str(bare), "-o", str(tmp_path / "m.npz")), "one bare array")
    damaged = tmp_path / "damaged.npz"
    np.savez_compressed(damaged, **good_arrays(ranges=np.random.default_rng(0).random((200, 300), np.float32)))
    data = bytearray(damaged.read_bytes())
    data[len(data) // 3 : len(data) // 3 + 64] = bytes(64)  # inside the compressed ranges
    damaged.write_bytes(bytes(data))
    _one_line_exit_2(posegrid("fuse", str(damaged), "-o", str(tmp_path / "m.npz")), "not a readable")
    assert not (tmp_path / "m.npz").exists()


@pytest.fixture(scope="module")
def map_arrays(posed_file, tmp_path_factory) -> dict:
    path = tmp_path_factory.mktemp("map") / "map.npz"
    assert posegrid("fuse", str(posed_file), "-o", str(path)).returncode == 0
    with np.load(path) as data:
        return dict(data)


@pytest.mark.parametrize(
    "key, value, phrase",
    [
        ("probability", "text", "'probability' must hold real numbers"),
        ("probability", np.nan, "'probability' holds nan"),
        ("probability", 1.5, "in [0, 1]"),
        ("probability", 0.97, "'probability' is not the logistic of 'logodds': at (0, 0) it holds 0.97"),
        ("variance", -1.0, "'variance' holds -1"),
        ("observed", "text", "'observed' must be boolean"),
        ("observed", 2, "'observed' must be boolean"),
        ("level", 1000, "'level' holds 1000"),
        ("level", 0.5, "'level' must hold integers"),
    ],
)
def test_map_layers_out_of_their_range_are_one_line(map_arrays, tmp_path, key, value, phrase):
    arrays = dict(map_arrays)
    shape = arrays["logodds"].shape
    if isinstance(value, str):
        arrays[key] = np.full(shape, value)
    else:  # the layer as written (a zero level where the map has none), one cell set to ``value``
        arrays[key] = np.array(arrays.get(key, np.zeros(shape)), dtype=np.asarray(value).dtype)
        arrays[key][0, 0] = value
    path = _bad(tmp_path, "bad-map.npz", **arrays)
    _one_line_exit_2(posegrid("export", str(path), "--format", "png", "-o", str(tmp_path / "m.png")), phrase)
    assert not (tmp_path / "m.png").exists()


@pytest.mark.parametrize(
    "key, value, phrase",
    [
        ("resolution", 1e-300, "'resolution' must be in [1e-06, 1000] m"),  # map_server would read 0.000000
        ("origin", np.array([1e12, 0.0]), "'origin' must be 2 finite numbers (x, y) in m within +-1e+09"),
    ],
)
def test_a_map_frame_no_cell_index_can_follow_is_one_line(map_arrays, tmp_path, key, value, phrase):
    path = _bad(tmp_path, "bad-frame.npz", **{**map_arrays, key: value})
    _one_line_exit_2(posegrid("export", str(path), "--format", "pgm", "-o", str(tmp_path / "m.pgm")), phrase)


def test_an_empty_map_exports_no_image(map_arrays, tmp_path):
    empty = {
        **map_arrays,
        **{
            key: map_arrays[key][:0, :0]
            for key in ("logodds", "probability", "observed", "variance")
            if key in map_arrays
        },
    }
    path = _bad(tmp_path, "empty.npz", **empty)
    for fmt in ("pgm", "png"):
        _one_line_exit_2(posegrid("export", str(path), "--format", fmt, "-o", str(tmp_path / f"m.{fmt}")), "empty")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["empty.npz"]


def test_sample_counts_for_a_file_of_samples_are_refused(tmp_path):
    """Samples are fused as they are; --samples, --accuracy and --seed only draw from Gaussian poses (a --seed
    given with a file of samples was taken and changed nothing)."""
    path = _bad(tmp_path, "samples.npz", **good_arrays())
    for option in (["--samples", "5"], ["--accuracy", "0.1"], ["--seed", "7"]):
        _one_line_exit_2(posegrid("fuse", str(path), "-o", str(tmp_path / "m.npz"), *option), "holds pose samples")


def test_truth_of_one_class_scores_auc_null_and_a_nan_origin_is_one_line(tmp_path, posed_file):
    map_path = tmp_path / "map.npz"
    assert posegrid("fuse", str(posed_file), "-o", str(map_path)).returncode == 0
    walls = np.ones((60, 80), bool)
    save_truth(tmp_path / "walls.npz", TruthRaster(walls, walls, np.zeros(2), 0.05))
    one_class = posegrid("eval", str(map_path), str(tmp_path / "walls.npz"))
    scores = json.loads(one_class.stdout)  # valid JSON: no NaN
    assert one_class.returncode == 0 and scores["auc"] is None and scores["n"] == walls.size
    assert 0 < scores["brier"] < 1 and "one class only" in one_class.stderr
    np.savez(tmp_path / "nan.npz", occupied=walls, visible=walls, origin=np.array([np.nan, 0.0]), resolution=0.05)
    _one_line_exit_2(posegrid("eval", str(map_path), str(tmp_path / "nan.npz")), "'origin' must be 2 finite")
    # a cell past 2^25: a 778 KB file of 20 000 x 20 000 visible cells took eval past 19 GB
    huge = np.zeros((2**12, 2**13 + 1), bool)
    np.savez_compressed(tmp_path / "huge.npz", occupied=huge, visible=~huge, origin=np.zeros(2), resolution=0.05)
    _one_line_exit_2(posegrid("eval", str(map_path), str(tmp_path / "huge.npz")), "4096 x 8193 cells, more than")


def test_export_names_must_fit_the_format(posed_file, tmp_path):
    """A pgm's YAML goes beside it as NAME.yaml: -o map.yaml would have been overwritten by it."""
    map_path = tmp_path / "map.npz"
    assert posegrid("fuse", str(posed_file), "-o", str(map_path)).returncode == 0
    _one_line_exit_2(
        posegrid("export", str(map_path), "--format", "pgm", "-o", str(tmp_path / "same.yaml")),
        "needs a name ending in .pgm",
    )
    _one_line_exit_2(
        posegrid("export", str(map_path), "--format", "png", "-o", str(tmp_path / "m.pgm")),
        "needs a name ending in .png",
    )
    _one_line_exit_2(
        posegrid("export", str(map_path), "--format", "pgm", "-o", str(tmp_path / "m.pgm"), "--layer", "variance"),
        "--layer variance draws a png",
    )
    assert sorted(p.name for p in tmp_path.iterdir()) == ["map.npz"]


def test_outputs_are_written_at_the_given_name_and_never_in_part(posed_file, tmp_path):
    plain = tmp_path / "map-without-suffix"
    assert posegrid("fuse", str(posed_file), "-o", str(plain)).returncode == 0
    assert load_map(plain).logodds.size and not Path(f"{plain}.npz").exists()

    def fails_halfway(handle):
        handle.write(b"half a map")
        raise OSError(28, "No space left on device")

    with pytest.raises(OSError, match="No space left on device") as failure:
        write_atomically(tmp_path / "out.npz", fails_halfway)
    assert failure.value.filename == str(tmp_path / "out.npz")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["map-without-suffix"]


def test_poses_a_loader_would_refuse_are_not_written(tmp_path):
    """A filter that diverged to NaN must not leave a file that every reader then refuses."""
    bad = PoseDistributionFile(
        stamps=np.arange(2.0),
        poses=PoseSet(mean=np.array([[0.0, 0.0, 0.0], [np.nan, 0, 0]]), cov=np.stack([np.eye(3)] * 2)),
    )
    with pytest.raises(FormatError, match=r"the poses to write to .*'mean' has NaN or inf at step 1"):
        save_pose_distribution(tmp_path / "poses.npz", bad)
    assert not (tmp_path / "poses.npz").exists()


def test_a_map_that_misses_the_truth_is_warned_about(tmp_path, map_arrays):
    """A map 100 m away from the truth scores the AUC of a blank map (0.5); eval says so rather than only print it."""
    map_path = tmp_path / "map.npz"
    np.savez(map_path, **map_arrays)
    occupied = np.zeros((60, 80), bool)
    occupied[::7] = True
    save_truth(tmp_path / "far.npz", TruthRaster(occupied, np.ones_like(occupied), np.array([100.0, 100.0]), 0.05))
    far = posegrid("eval", str(map_path), str(tmp_path / "far.npz"))
    scores = json.loads(far.stdout)
    assert far.returncode == 0 and scores["informed"] == 0 and scores["auc"] == 0.5 and scores["n"] == occupied.size
    assert "observed none of the truth's 4800 visible cells" in far.stderr
    save_truth(tmp_path / "near.npz", TruthRaster(occupied, np.ones_like(occupied), np.zeros(2), 0.05))
    near = posegrid("eval", str(map_path), str(tmp_path / "near.npz"))
    assert 0 < json.loads(near.stdout)["informed"] <= occupied.size and "warning" not in near.stderr


def test_a_scan_refused_midway_ends_the_progress_bar_before_the_error(tmp_path):
    """The error line came first and the bar's last state after it, on the same terminal line as the next prompt."""
    samples = np.zeros((60, 1, 3))
    samples[5, 0, 0] = 1e12  # scan 5's pose: beyond what the grid's cells can index
    arrays = good_arrays(
        ranges=np.ones((60, 3), np.float32), stamps=np.arange(60.0), samples=samples, weights=np.ones((60, 1))
    )
    result = posegrid("fuse", str(_bad(tmp_path, "far.npz", **arrays)), "-o", str(tmp_path / "m.npz"))
    last = result.stderr.replace("\r", "\n").strip().splitlines()[-1]
    assert result.returncode == 2 and last.startswith("posegrid fuse: error:") and "reaches beyond" in last, (
        result.stderr
    )


@pytest.mark.parametrize("gaussian", [False, True])
def test_a_run_too_wide_for_one_map_is_refused_before_it_is_fused(tmp_path, gaussian):
    """A probe: a run that crossed 5 km diagonally was fused whole, every scan, before `fuse` said the map's tiles
    spanned more cells than one raster may hold. The robot's positions alone say so up front."""
    posed = tmp_path / "far.npz"
    far = np.array([[0.0, 0.0, 0.0], [5000.0, 5000.0, 0.0]])
    poses = (
        {"mean": far, "cov": np.stack([np.eye(3) * 1e-4] * 2)}
        if gaussian
        else {"samples": far[:, None, :], "weights": np.ones((2, 1))}
    )
    np.savez(posed, ranges=np.ones((2, 3), np.float32), angle_min=0.0, angle_increment=0.1, range_min=0.1,
             range_max=5.0, stamps=np.arange(2.0), **poses)  # fmt: skip
    done = posegrid("fuse", str(posed), "-o", str(tmp_path / "map.npz"))
    assert done.returncode == 2 and "the robot's positions alone span more than" in done.stderr, done.stderr
    assert "nothing fused" in done.stderr and not (tmp_path / "map.npz").exists()
    # a scale probe: positions 64 tiles apart (820 m at 0.05 m) pass that check, but their 65 tiles a side do not fit;
    # found after the fusion, the library's own words ("read it tile by tile") told a fuse user nothing to do
    edge = np.array([[0.0, 0.0, 0.0], [64 * 12.8 + 1.0, 64 * 12.8 + 1.0, 0.0]])
    np.savez(posed, ranges=np.ones((2, 3), np.float32), angle_min=0.0, angle_increment=0.1, range_min=0.1,
             range_max=5.0, stamps=np.arange(2.0), samples=edge[:, None, :], weights=np.ones((2, 1)))  # fmt: skip
    done = posegrid("fuse", str(posed), "-o", str(tmp_path / "map.npz"))
    assert done.returncode == 2 and "the map's tiles span 16640 x 16640 cells" in done.stderr, done.stderr
    assert "fuse it in parts" in done.stderr and f"nothing written to {tmp_path / 'map.npz'}" in done.stderr
    assert "Traceback" not in done.stderr and not (tmp_path / "map.npz").exists()
    near = far * [0.01, 0.01, 1.0]  # (50 m: fused)
    np.savez(posed, ranges=np.ones((2, 3), np.float32), angle_min=0.0, angle_increment=0.1, range_min=0.1,
             range_max=5.0, stamps=np.arange(2.0), samples=near[:, None, :], weights=np.ones((2, 1)))  # fmt: skip
    assert posegrid("fuse", str(posed), "-o", str(tmp_path / "map.npz")).returncode == 0


def test_progress_bars_stay_out_of_a_pipe(posed_file, tmp_path):
    """A probe: `posegrid fuse` (and `posegrid slam --algo gridslam`) wrote its progress bar's carriage-return lines
    into a log file or pipe, where `posegrid run` and `posegrid slam`'s landmark filters wrote none."""
    done = posegrid_process("fuse", str(posed_file), "-o", str(tmp_path / "map.npz"))
    assert done.returncode == 0 and "\r" not in done.stderr and "fusing" not in done.stderr, done.stderr
