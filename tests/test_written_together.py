"""Outputs of several files are written together or not at all (schemas.files.written_together), and a write that
fails leaves the old file (write_atomically), whatever the command.

A probe filled the disk while commands wrote: `posegrid export --format pgm` left the new image beside the old map's
YAML (map_server would load it at the wrong scale), `posegrid simulate` left one seed's scans and truth beside another
seed's ground truth, controls and landmarks (and `slam` ran on the mix without a word), and `posegrid calibrate`
replaced a good calibration by a truncated one. The commands here run as processes under a file-size limit
(RLIMIT_FSIZE), so that a write past it fails with EFBIG, as on a full disk."""

from __future__ import annotations

import contextlib
import errno
import resource
import subprocess
from pathlib import Path

import pytest

from schemas.files import write_atomically, written_together
from test_cli_mapping import posegrid_process


def _posegrid(*args: str, file_limit: int | None = None) -> subprocess.CompletedProcess:
    """`posegrid ARGS` as a process of its own, its files limited to ``file_limit`` bytes (None: no limit)."""

    def limit() -> None:
        if file_limit is not None:  # (Python ignores SIGXFSZ: a write past the limit fails with EFBIG)
            resource.setrlimit(resource.RLIMIT_FSIZE, (file_limit, file_limit))

    return posegrid_process(*args, preexec_fn=limit)


def _contents(folder: Path) -> dict[str, bytes]:
    return {path.name: path.read_bytes() for path in sorted(folder.iterdir())}


def test_files_written_together_move_into_place_only_when_all_are_written(tmp_path):
    first, second = tmp_path / "a.pgm", tmp_path / "a.yaml"
    first.write_bytes(b"old image")
    second.write_bytes(b"old yaml")

    def full_disk(handle):
        handle.write(b"half a yaml")
        raise OSError(errno.ENOSPC, "No space left on device")

    with pytest.raises(OSError, match="No space left on device") as failure, written_together():
        write_atomically(first, lambda handle: handle.write(b"new image"))
        assert first.read_bytes() == b"old image"  # (written beside it, not moved yet)
        write_atomically(second, full_disk)
    assert failure.value.filename == str(second)
    assert _contents(tmp_path) == {"a.pgm": b"old image", "a.yaml": b"old yaml"}  # no partial file either

    with pytest.raises(ValueError, match="made up"), written_together():  # an error in the block: the same
        write_atomically(first, lambda handle: handle.write(b"new image"))
        raise ValueError("made up")
    assert _contents(tmp_path) == {"a.pgm": b"old image", "a.yaml": b"old yaml"}

    with written_together():
        write_atomically(first, lambda handle: handle.write(b"new image"))
        write_atomically(second, lambda handle: handle.write(b"new yaml"))
    assert _contents(tmp_path) == {"a.pgm": b"new image", "a.yaml": b"new yaml"}
    with pytest.raises(RuntimeError, match="do not nest"), contextlib.ExitStack() as stack:
        stack.enter_context(written_together())
        stack.enter_context(written_together())


def test_simulate_on_a_full_disk_leaves_the_folders_old_run_whole(tmp_path):
    """scans.npz (about 3 KB here) fits under the limit, truth.npz (about 4.5 KB) does not: before, the folder then
    held the new seed's scans beside the old seed's other files."""
    folder = tmp_path / "sim"
    small = ("--steps", "20", "--beams", "10")
    assert _posegrid("simulate", str(folder), *small, "--seed", "0").returncode == 0
    old = _contents(folder)
    assert len(old["scans.npz"]) < 4000 < len(old["truth.npz"])  # (what the limit below relies on)
    done = _posegrid("simulate", str(folder), *small, "--seed", "1", file_limit=4000)
    assert done.returncode == 2 and "File too large" in done.stderr and "truth.npz" in done.stderr, done.stderr
    assert "Traceback" not in done.stderr
    assert _contents(folder) == old
    assert _posegrid("simulate", str(folder), *small, "--seed", "1").returncode == 0
    assert _contents(folder)["scans.npz"] != old["scans.npz"]  # (the seed does change it)


def test_calibrate_on_a_full_disk_leaves_the_old_calibration(tmp_path):
    from slam.calibration import GENERIC, load_calibration
    from slam.mrclam_sim import simulate_mrclam_robot, write_mrclam_folder

    folder = write_mrclam_folder(tmp_path / "robot", simulate_mrclam_robot(GENERIC, seed=1, duration=60.0))
    out = tmp_path / "cal.json"
    assert _posegrid("calibrate", str(folder), "--robot", "1", "-o", str(out)).returncode == 0
    old = out.read_bytes()
    assert len(old) > 1000
    done = _posegrid("calibrate", str(folder), "--robot", "1", "-o", str(out), file_limit=1000)
    assert done.returncode == 2 and f"File too large ({out})" in done.stderr, done.stderr
    assert out.read_bytes() == old and sorted(p.name for p in tmp_path.iterdir()) == ["cal.json", "robot"]
    load_calibration(out)
