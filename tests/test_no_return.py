"""Beams with no return: how far they clear free space (the no-return range), from the fusion's cells to what a
real log's source, `posegrid slam` and the ROS 2 bridge send (docs/sensor_model.md, section 3). The fusion against the
slow reference for any no-return range: tests/test_fusion.py."""

from __future__ import annotations

import math

import numpy as np
import pytest

from conftest import shared_file
from mapping.adaptive.fusion import AdaptiveFusion
from mapping.adaptive.tree import AdaptiveGrid
from mapping.errors import InputError
from mapping.fusion import MonteCarloFusion
from mapping.grid import TiledGrid
from mapping.sensor_model import SensorModel
from schemas.files import load_posed_scans
from schemas.messages import LaserScan
from services.cli import main
from services.commands.gridslam import posed_no_returns
from services.ros2 import convert
from slam.carmen import read_carmen, write_carmen_scans
from slam.laserlog import NO_RETURN_RANGE
from slam.simulator import simulate_office
from test_cli_mapping import posegrid
from test_fusion import fused_cells


def _beam_cells(no_return_range: float | None, sigma: str) -> set[tuple[int, int]]:
    """The observed cells of one scan at (0.05, 0.05) facing +x with 0.1 m cells, range_max 2 m: a beam along +x
    with no return (inf) and one along +y whose return lies at 0.5 m."""
    model = SensorModel(resolution=0.1, sigma=sigma, sigma0=0.02, sigma_slope=0.01 if sigma == "linear" else 0.0)
    grid = TiledGrid(0.1, tile_size=8)
    fusion = MonteCarloFusion(grid, model, np.array([0.0, math.pi / 2]), 0.05, 2.0, no_return_range=no_return_range)
    fusion.fuse(np.array([np.inf, 0.5]), np.array([[0.05, 0.05, 0.0]]), np.ones(1))
    return set(fused_cells(grid))


@pytest.mark.parametrize("sigma", ["constant", "linear"])  # (the compiled beam table and numpy's)
def test_a_beam_with_no_return_clears_the_cells_up_to_its_no_return_range(sigma):
    """Hand-counted: the beam along +x from x = 0.05 m reaches r at x = 0.05 + r, so a no-return range of 1 m ends
    in cell 10 ([1.0, 1.1) m) and range_max, 2 m, in cell 20; a no-return range of 0 leaves the beam out. The beam
    with a return is the same whatever the no-return range."""
    hit_beam = _beam_cells(0.0, sigma)
    assert hit_beam and all(ix == 0 for ix, _ in hit_beam)  # the +y beam's cells only
    assert _beam_cells(1.0, sigma) - hit_beam == {(ix, 0) for ix in range(1, 11)}
    assert _beam_cells(None, sigma) == _beam_cells(2.0, sigma)
    assert _beam_cells(2.0, sigma) - hit_beam == {(ix, 0) for ix in range(1, 21)}


@pytest.mark.parametrize("clears", [-0.5, 2.5, math.nan, math.inf])
def test_a_no_return_range_outside_zero_to_range_max_is_refused(clears):
    model = SensorModel(resolution=0.1)
    with pytest.raises(InputError, match="no-return range"):
        MonteCarloFusion(TiledGrid(0.1), model, np.zeros(3), 0.05, 2.0, no_return_range=clears)
    with pytest.raises(InputError, match="no-return range"):
        AdaptiveFusion(AdaptiveGrid(0.1), model, np.zeros(3), 0.05, 2.0, no_return_range=clears)


def test_posed_scans_say_a_no_return_range_as_the_file_format_can():
    """The posed-scan format clears a beam with no return up to the file's range_max: a no-return range of 0 is
    written as 0 (no reading), one below the scans' limit as their range_max; NaN (past a row's beams) stays."""
    ranges = np.array([[1.0, np.inf, 35.0, 90.0, np.nan]], np.float32)  # the laser states 80 m, mapped to 30
    stated, limit = np.array([80.0]), np.array([30.0])
    written, range_max = posed_no_returns(ranges, stated, limit, 0.0)
    np.testing.assert_array_equal(written, [[1.0, 0.0, 35.0, 0.0, np.nan]])
    np.testing.assert_array_equal(range_max, [30.0])
    written, range_max = posed_no_returns(ranges, stated, limit, 5.0)
    np.testing.assert_array_equal(written, ranges)
    np.testing.assert_array_equal(range_max, [5.0])
    assert posed_no_returns(ranges, stated, limit, 50.0)[1].tolist() == [30.0]


@pytest.fixture(scope="module")
def office_log(tmp_path_factory):
    """A simulated office run of 40 scans with an 8 m laser as a CARMEN log (its beams with no return: +inf)."""
    run = simulate_office(seed=3, steps=40, n_beams=91, range_max=8.0)
    path = tmp_path_factory.mktemp("office") / "office.clf"
    write_carmen_scans(path, run)
    assert np.isinf(read_carmen(path).ranges).any()
    return path


def test_posegrid_slam_writes_a_logs_beams_with_no_return_as_the_option_says(office_log, tmp_path, capsys):
    """By default the posed scans carry the log's beams with no return as 0 (they say nothing), and the note says
    how many there are; with --no-return-range 4 they stay +inf under a range_max of 4 m. Another algorithm refuses
    the option, which it would ignore."""
    log = read_carmen(office_log)
    argv = ["slam", "--algo", "gridslam", str(office_log), "--particles", "2", "--particle-cap", "2"]
    assert main([*argv, "-o", str(tmp_path / "zero.npz")]) == 0
    assert "of its beams have no return; they clear no free space" in capsys.readouterr().err
    zero = load_posed_scans(tmp_path / "zero.npz")
    kept = np.isin(log.stamps, zero.stamps)
    expected = np.where(np.isinf(log.ranges[kept]), 0.0, log.ranges[kept])
    np.testing.assert_array_equal(zero.ranges, expected)
    assert zero.range_max == pytest.approx(8.0)
    assert main([*argv, "-o", str(tmp_path / "four.npz"), "--no-return-range", "4"]) == 0
    four = load_posed_scans(tmp_path / "four.npz")
    np.testing.assert_array_equal(four.ranges, log.ranges[kept])
    assert four.range_max == pytest.approx(4.0)
    assert main(["slam", "--algo", "ekf", str(office_log), "-o", str(tmp_path / "e.npz"), "--no-return-range", "4"])
    assert "--no-return-range only apply to grid FastSLAM" in capsys.readouterr().err


@pytest.mark.parametrize(
    ("argv", "said"),
    [
        (["source", "--sim", "--no-return-range", "5"], "give it with --carmen or --bag"),
        (["run", "--no-return-range", "5", "--no-api"], "give it with --carmen or --bag"),
        (["source", "--carmen", "x.clf", "--no-return-range", "-1"], "expected metres in [0, 10000], got -1"),
        (["source", "--carmen", "x.clf", "--no-return-range", "nan"], "must be a finite number, got 'nan'"),
        (["ros2", "--no-return-range", "far", "--connect", "tcp/127.0.0.1:1"], "'far' is not a number"),
    ],
)
def test_a_misplaced_or_bad_no_return_range_is_one_line_and_exit_2(argv, said):
    done = posegrid(*argv)
    err = done.stderr.strip().splitlines()
    assert done.returncode == 2 and err and said in err[-1] and "Traceback" not in done.stderr, err


def _ros_scan(ranges, range_max: float = 10.0):
    from services.ros2 import types as rt

    return rt.MessageType(rt.LASER_SCAN).cls()(
        header=convert.header(1.0, "laser"),
        angle_min=-1.0,
        angle_max=0.0,
        angle_increment=0.5,
        time_increment=0.0,
        scan_time=0.0,
        range_min=0.1,
        range_max=range_max,
        ranges=np.array(ranges, np.float32),
        intensities=np.zeros(0, np.float32),
    )


@pytest.mark.parametrize(("clears", "sent"), [(0.0, 0.0), (4.0, 4.0), (25.0, 10.0)])
def test_the_bridge_sends_a_ros_scans_no_return_range_within_its_range_max(clears, sent):
    from slam.rosbag_reader import Mount

    scan = convert.to_laser_scan(_ros_scan([1.0, np.inf, 12.0]), "r1", 0, Mount((0.0, 0.0, 0.0), False), clears)
    assert scan.no_return_range == sent and scan.ranges.tolist() == [1.0, np.inf, np.inf]
    convert.encoded(scan, "geometry")  # the wire takes it


def test_a_real_logs_source_clears_nothing_past_its_returns(capsys):
    """The corrected Intel log states 80 m and returns at most 25.4 m; 2.6 % of its beams have no return, many of
    them at walls their neighbours hit. What its source publishes, fused at the log's own poses (its first 300
    scans): by default no observed cell lies farther from the laser than the farthest return and the model's tail;
    let those beams clear to the stated 80 m and cells 60 m and more out are marked free."""
    from scipy.spatial import cKDTree

    from services.streams import laser_log_stream

    log = read_carmen(shared_file("intel-lab", "intel-corrected.log.gz")).first(300)
    model = SensorModel()
    yaw, offset = log.poses[:, 2], log.sensor_offset
    lasers = log.poses[:, :2] + np.column_stack(  # where the laser stood at each scan, m
        [
            np.cos(yaw) * offset[:, 0] - np.sin(yaw) * offset[:, 1],
            np.sin(yaw) * offset[:, 0] + np.cos(yaw) * offset[:, 1],
        ]
    )
    farthest = float(log.ranges[np.isfinite(log.ranges)].max())

    def reach(no_return_range: float) -> float:
        """The farthest observed cell's centre from the nearest laser position, m."""
        stream = laser_log_stream(log, "intel", no_return_range)
        scans = [m for step in stream.steps for m in step.messages if isinstance(m, LaserScan)]
        assert {m.no_return_range for m in scans} == {min(no_return_range, 80.0)}
        grid = TiledGrid(model.resolution)
        first = scans[0]
        angles = first.angle_min + first.angle_increment * np.arange(first.ranges.shape[0])
        fusion = MonteCarloFusion(
            grid,
            model,
            angles,
            first.range_min,
            first.range_max,
            first.sensor_offset,
            no_return_range=first.no_return_range,
        )
        for t, scan in enumerate(scans):
            fusion.fuse(scan.ranges, log.poses[t : t + 1], np.ones(1))
        raster = grid.rasterize()
        rows, cols = np.nonzero(raster["observed"])
        centres = raster["origin"] + (np.column_stack([cols, rows]) + 0.5) * model.resolution
        return float(cKDTree(lasers).query(centres)[0].max())

    assert reach(NO_RETURN_RANGE) <= farthest + 0.5
    assert reach(80.0) > 60.0


@pytest.mark.parametrize(("argv", "clears"), [([], NO_RETURN_RANGE), (["--no-return-range", "3.5"], 3.5)])
def test_the_bridges_ingest_takes_the_no_return_range_given(argv, clears):
    """`posegrid ros2` (and `run --ros2`, whose bridge child it starts) hands --no-return-range to its ingest."""
    from services.cli import build_parser
    from services.commands.ros2 import bridge_options

    args = build_parser().parse_args(["ros2", "--connect", "tcp/127.0.0.1:1", *argv])
    assert bridge_options(args).ingest.no_return_range == clears


@pytest.mark.parametrize(
    ("options", "clears"), [([], "30.0"), (["--max-range", "12"], "12.0"), (["--max-range", "90"], "50.0")]
)
def test_run_clears_a_logs_beams_with_no_return_at_most_to_grid_fastslams_max_range(office_log, options, clears):
    """A real-log probe: `run --carmen LOG --no-return-range 50` cleared up to 50 m where `posegrid slam --algo
    gridslam` (whose --max-range, 30 m by default, caps every beam it writes) cleared up to 30, so the live map and
    the offline map of the same log and options differed (IoU 0.38). The run hands its source the capped range."""
    from services.cli import build_parser
    from services.commands.pipeline import _plan_input
    from services.nodes.launcher import Plan

    args = build_parser().parse_args(["run", "--carmen", str(office_log), "--no-return-range", "50", *options])
    plan = Plan(map_name="main", robot="robot0", shards=1, resolution=0.05, mapper_argv=[], source_argv=[])
    _plan_input(args, plan)
    at = plan.source_argv.index("--no-return-range")
    assert plan.source_argv[at + 1] == clears
