"""`posegrid fuse / export / eval` as a user runs them: real processes, real files."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from schemas.files import TruthRaster, load_map, save_posed_scans, save_truth
from worlds import room_posed_scans

ROOT = Path(__file__).resolve().parents[1]


def posegrid(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "services.cli", *args], cwd=ROOT, capture_output=True, text=True,
                          timeout=300)


@pytest.fixture(scope="module")
def posed_file(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("posed") / "room.npz"
    save_posed_scans(path, room_posed_scans(steps=10, beams=120))
    return path


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
    assert "image: m.pgm" in (tmp_path / "m.yaml").read_text()
    for layer in ("probability", "variance"):
        result = posegrid("export", str(map_path), "--format", "png", "-o", str(tmp_path / f"{layer}.png"),
                          "--layer", layer)
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
    arrays = dict(ranges=np.ones((2, 3), np.float32), angle_min=0.0, angle_increment=0.1, range_min=0.1,
                  range_max=5.0, stamps=np.arange(2.0), samples=np.zeros((2, 1, 3)), weights=np.ones((2, 1)))
    arrays.update(override)
    return {k: v for k, v in arrays.items() if v is not None}


@pytest.mark.parametrize("arrays, phrase", [
    (good_arrays(weights=np.full((2, 1), 0.5)), "sum to"),
    (good_arrays(samples=np.full((2, 1, 3), np.nan)), "NaN"),
    (good_arrays(ranges=np.ones(3, np.float32)), "shape (T, B)"),
    (good_arrays(stamps=None), "missing key 'stamps'"),
    (good_arrays(samples=np.zeros((2, 1, 2))), "'samples' must have shape"),
    (good_arrays(range_max=0.05), "range_min < range_max"),
])
def test_malformed_posed_files_exit_2_with_one_line(tmp_path, arrays, phrase):
    result = posegrid("fuse", str(_bad(tmp_path, "bad.npz", **arrays)), "-o", str(tmp_path / "m.npz"))
    assert result.returncode == 2
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and phrase in lines[0] and "Traceback" not in result.stderr


def test_not_an_npz_and_missing_file(tmp_path):
    junk = tmp_path / "junk.npz"
    junk.write_text("hello")
    for path in (junk, tmp_path / "absent.npz"):
        result = posegrid("fuse", str(path), "-o", str(tmp_path / "m.npz"))
        assert result.returncode == 2 and len(result.stderr.strip().splitlines()) == 1


def test_bad_option_value_exit_2(posed_file, tmp_path):
    result = posegrid("fuse", str(posed_file), "-o", str(tmp_path / "m.npz"), "--sigma0", "-1")
    assert result.returncode == 2 and "sigma0" in result.stderr
