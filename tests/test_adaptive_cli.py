"""`posegrid fuse --grid adaptive` writes the same map file contract, with the `level` layer."""

from __future__ import annotations

import numpy as np
import pytest

from mapping.evaluation import score_map
from mapping.export import render_pgm
from schemas.files import load_map, save_posed_scans
from services.cli import main
from worlds import room_posed_scans


@pytest.fixture(scope="module")
def posed_file(tmp_path_factory):
    path = tmp_path_factory.mktemp("posed") / "room.npz"
    save_posed_scans(path, room_posed_scans(steps=6, beams=120))
    return path


def test_adaptive_map_file_holds_levels_and_works_with_the_tools(posed_file, tmp_path, capsys):
    regular, adaptive, einhorn = tmp_path / "regular.npz", tmp_path / "adaptive.npz", tmp_path / "einhorn.npz"
    assert main(["fuse", str(posed_file), "-o", str(regular), "--samples", "8"]) == 0
    assert main(["fuse", str(posed_file), "-o", str(adaptive), "--samples", "8", "--grid", "adaptive"]) == 0
    out = capsys.readouterr().out
    assert (
        main(
            [
                "fuse",
                str(posed_file),
                "-o",
                str(einhorn),
                "--samples",
                "8",
                "--grid",
                "adaptive",
                "--no-unknowns",
                "--coarse-cell",
                "0.4",
            ]
        )
        == 0
    )
    fine, tree, other = load_map(regular), load_map(adaptive), load_map(einhorn)
    assert fine.level is None and tree.level is not None and tree.level.dtype == np.int8
    # the raster is the finest resolution; every observed cell belongs to one active cell
    assert float(tree.resolution) == pytest.approx(0.05)
    assert ((tree.level >= 0) == tree.observed).all() and (tree.level == 4).any()
    active = (4.0 ** -tree.level[tree.observed].astype(float)).sum()
    assert f"{int(round(active))} active cells (with unknowns)" in out
    assert active < 0.5 * fine.observed.sum()
    assert (other.level == 3).any() and not np.array_equal(other.level, tree.level)
    # the tools read it unchanged: scoring against the regular map's occupancy, and the PGM export
    truth = {
        "occupied": fine.probability > 0.5,
        "visible": fine.observed,
        "origin": fine.origin,
        "resolution": fine.resolution,
    }
    assert score_map(vars(tree), truth)["auc"] > 0.9
    pgm, _ = render_pgm(vars(tree))
    assert pgm.startswith(b"P5")


def test_bad_adaptive_options_are_usage_errors(posed_file, tmp_path, capsys):
    out = str(tmp_path / "m.npz")
    assert main(["fuse", str(posed_file), "-o", out, "--grid", "adaptive", "--coarse-cell", "0.3"]) == 2
    assert (
        "--coarse-cell 0.3 m must be --resolution 0.05 m times a power of two, at most 12.8 m"
        in capsys.readouterr().err
    )
    # (a probe: a coarse cell past a tile said "need 0 <= start_level <= max_level <= 8 (a tile), got 13 and 8", and
    # a --resolution the default coarse cell is no multiple of blamed a 0.8 m cell the user never gave)
    assert main(["fuse", str(posed_file), "-o", out, "--grid", "adaptive", "--coarse-cell", "409.6"]) == 2
    assert (
        "--coarse-cell 409.6 m is coarser than a tile: at most 12.8 m at --resolution 0.05 m" in capsys.readouterr().err
    )
    assert main(["fuse", str(posed_file), "-o", out, "--grid", "adaptive", "--resolution", "10"]) == 2
    assert "--coarse-cell (default) 0.8 m must be --resolution 10 m times a power of two" in capsys.readouterr().err
    assert main(["fuse", str(posed_file), "-o", out, "--grid", "adaptive", "--significance", "2"]) == 2
    assert "significance" in capsys.readouterr().err
    for option in (["--no-unknowns"], ["--coarse-cell", "0.4"], ["--significance", "0.1"], ["--unknown-range", "1"]):
        assert main(["fuse", str(posed_file), "-o", out, *option]) == 2  # a regular grid would ignore it
        assert "shape the adaptive grid only; add --grid adaptive" in capsys.readouterr().err
    assert not (tmp_path / "m.npz").exists()


def test_unknown_range_reaches_the_split_test(posed_file, tmp_path):
    from mapping.adaptive import AdaptiveParams
    from schemas.files import load_posed_scans
    from services.fusion_runner import fuse_posed_scans_adaptive

    out = tmp_path / "short.npz"
    assert (
        main(
            ["fuse", str(posed_file), "-o", str(out), "--samples", "8", "--grid", "adaptive", "--unknown-range", "0.3"]
        )
        == 0
    )
    expected = fuse_posed_scans_adaptive(
        load_posed_scans(posed_file), n_samples=8, params=AdaptiveParams(unknown_range=0.3)
    ).rasterize()
    default = fuse_posed_scans_adaptive(load_posed_scans(posed_file), n_samples=8).rasterize()
    assert not np.array_equal(expected["level"], default["level"])  # the option changes the tree here
    np.testing.assert_array_equal(load_map(out).level, expected["level"])


def test_bad_unknown_range_is_a_usage_error(posed_file, tmp_path, capsys):
    out = str(tmp_path / "m.npz")
    assert main(["fuse", str(posed_file), "-o", out, "--grid", "adaptive", "--unknown-range", "-1"]) == 2
    assert "unknown_range must be >= 0" in capsys.readouterr().err
    assert (
        main(["fuse", str(posed_file), "-o", out, "--grid", "adaptive", "--no-unknowns", "--unknown-range", "1"]) == 2
    )
    assert "drop one of them" in capsys.readouterr().err
