"""Output paths of every CLI command: checked before any work, written through a temporary file that is fsynced
and renamed onto a regular file only, and never reported as written when the write failed.

Every path here lies in tmp_path; /dev/full is only stat-ed (it must be refused before anything is written).
"""

from __future__ import annotations

import errno
import os
import signal
import stat
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import pytest

from schemas.files import load_map, output_path_problem, save_posed_scans, write_atomically
from services.cli import main
from services.commands.argtypes import refuse_another_kind
from services.errors import UsageError
from worlds import room_posed_scans

ROOT = Path(__file__).resolve().parents[1]
DEV_FULL = Path("/dev/full")


@pytest.fixture(scope="module")
def posed_file(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("posed") / "room.npz"
    save_posed_scans(path, room_posed_scans(steps=6, beams=90))
    return path


@pytest.fixture
def bad_outputs(tmp_path) -> dict[str, tuple[str, str]]:
    """Paths no command may write, in tmp_path: name -> (path, a phrase of the refusal)."""
    fifo = tmp_path / "fifo.png"
    os.mkfifo(fifo)
    (tmp_path / "folder.png").mkdir()
    (tmp_path / "to-fifo.png").symlink_to(fifo)
    return {
        "fifo": (str(fifo), "is a FIFO, not a regular file"),
        "folder": (str(tmp_path / "folder.png"), "is a folder, not a file"),
        "empty": ("", "an empty path names no file"),
        "missing folder": (str(tmp_path / "absent" / "out.png"), f"folder {tmp_path / 'absent'} does not exist"),
        "link to a fifo": (str(tmp_path / "to-fifo.png"), f"links to {fifo}, which is a FIFO"),
        # /proc takes no new file; its permissions pass for root (then the trial file says so), not for others
        "kernel file system": ("/proc/posegrid-out.png", "folder /proc"),
    }


def one_line_exit_2(argv: list[str], capsys, *fragments: str) -> str:
    """Run the CLI in this process; assert exit 2, nothing on stdout and one line on stderr holding fragments."""
    code = main(argv)
    captured = capsys.readouterr()
    err = captured.err.strip()
    assert code == 2 and "\n" not in err and "Traceback" not in err and captured.out == "", captured
    for fragment in fragments:
        assert fragment in err, err
    return err


def special_files_unchanged(tmp_path: Path) -> None:
    assert stat.S_ISFIFO(os.lstat(tmp_path / "fifo.png").st_mode)
    assert (tmp_path / "folder.png").is_dir() and not any((tmp_path / "folder.png").iterdir())
    assert os.path.islink(tmp_path / "to-fifo.png")
    assert not list(tmp_path.glob(".*partial"))


# The input of each command does not exist (its name holds "no-input"): the output's refusal, not the input's,
# shows the output is checked before anything is read.
COMMANDS = {
    "fuse": lambda tmp, out: ["fuse", str(tmp / "no-input.npz"), "-o", out],
    "export": lambda tmp, out: ["export", str(tmp / "no-input.npz"), "--format", "png", "-o", out],
    "slam": lambda tmp, out: ["slam", "--algo", "ekf", str(tmp / "no-input"), "-o", out],
    "slam gridslam -o": lambda tmp, out: ["slam", "--algo", "gridslam", str(tmp / "no-input.clf"), "-o", out],
    "slam gridslam --stats": lambda tmp, out: [
        "slam",
        "--algo",
        "gridslam",
        str(tmp / "no-input.clf"),
        "-o",
        str(tmp / "g.npz"),
        "--stats",
        out,
    ],
    "slam gridslam --best-output": lambda tmp, out: [
        "slam",
        "--algo",
        "gridslam",
        str(tmp / "no-input.clf"),
        "-o",
        str(tmp / "g.npz"),
        "--best-output",
        out,
    ],
    "slam gridslam --poses-output": lambda tmp, out: [
        "slam",
        "--algo",
        "gridslam",
        str(tmp / "no-input.clf"),
        "-o",
        str(tmp / "g.npz"),
        "--poses-output",
        out,
    ],
    "eval-relations --json": lambda tmp, out: [
        "eval-relations",
        str(tmp / "no-input.npz"),
        str(tmp / "no-input.txt"),
        "--json",
        out,
    ],
    "run --export": lambda tmp, out: ["run", "--posed", str(tmp / "no-input.npz"), "--no-api", "--export", out],
}


@pytest.mark.parametrize("command", COMMANDS)
@pytest.mark.parametrize("kind", ["fifo", "folder", "empty", "missing folder", "link to a fifo", "kernel file system"])
def test_every_output_is_checked_before_any_work(tmp_path, bad_outputs, capsys, command, kind):
    path, phrase = bad_outputs[kind]
    err = one_line_exit_2(COMMANDS[command](tmp_path, path), capsys, phrase)
    assert "no-input" not in err  # the input was never read
    special_files_unchanged(tmp_path)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["fifo.png", "folder.png", "to-fifo.png"]


def test_the_yaml_beside_a_pgm_is_checked_too(tmp_path, capsys):
    (tmp_path / "m.yaml").mkdir()
    one_line_exit_2(
        ["export", str(tmp_path / "no-input.npz"), "--format", "pgm", "-o", str(tmp_path / "m.pgm")],
        capsys,
        "the map_server YAML beside -o",
        f"{tmp_path / 'm.yaml'}: is a folder",
    )


def test_the_derived_gridslam_outputs_are_checked_too(tmp_path, capsys):
    os.mkfifo(tmp_path / "g.best.npz")
    one_line_exit_2(
        ["slam", "--algo", "gridslam", str(tmp_path / "no-input.clf"), "-o", str(tmp_path / "g.npz")],
        capsys,
        "--best-output's default",
        "is a FIFO",
    )


def test_simulate_checks_its_folder_and_files_before_simulating(tmp_path, capsys):
    folder = tmp_path / "sim"
    folder.mkdir()
    os.mkfifo(folder / "truth.npz")
    one_line_exit_2(
        ["simulate", str(folder), "--steps", "5", "--beams", "5"], capsys, str(folder / "truth.npz"), "is a FIFO"
    )
    assert [p.name for p in folder.iterdir()] == ["truth.npz"]  # scans.npz, written first, was not written
    (tmp_path / "file").write_text("x")
    one_line_exit_2(["simulate", str(tmp_path / "file")], capsys, "not a folder")
    one_line_exit_2(["simulate", ""], capsys, "an empty path names no folder")


def test_simulate_refuses_a_folder_of_another_dataset(tmp_path, capsys):
    """A new user's probe: `simulate` into a copy of an MRCLAM folder wrote its files beside the tables, and `slam`
    then read the folder as the simulation (the MRCLAM data no longer reachable through it). A folder holding a
    dataset's files (MRCLAM tables, a ROS 2 bag) is refused and left as it was."""
    for name in ("Robot1_Odometry.dat", "metadata.yaml"):
        folder = tmp_path / name.split(".")[0]
        folder.mkdir()
        (folder / name).write_text("1 2 3\n")
        one_line_exit_2(["simulate", str(folder), "--steps", "5"], capsys, "holds another dataset's files", name)
        assert [p.name for p in folder.iterdir()] == [name]
    (tmp_path / "notes").mkdir()
    (tmp_path / "notes" / "README.txt").write_text("mine")
    assert main(["simulate", str(tmp_path / "notes"), "--steps", "5", "--beams", "5"]) == 0  # (other files: taken)


def test_dev_full_is_refused_up_front_and_stays_a_device(posed_file, tmp_path, capsys):
    """/dev/full is only stat-ed and reached through a link in tmp_path (a writer that renamed onto its output
    would replace the link, not the device), and named directly only once the writer is shown to refuse every
    special file, so that no version of the code under test can replace the device."""
    if not DEV_FULL.exists():
        pytest.skip("no /dev/full here")
    assert stat.S_ISCHR(os.stat(DEV_FULL).st_mode)
    assert "is a character device" in output_path_problem(DEV_FULL)
    link = tmp_path / "full.npz"
    link.symlink_to(DEV_FULL)
    one_line_exit_2(
        ["fuse", str(posed_file), "-o", str(link)], capsys, "links to /dev/full, which is a character device"
    )
    with pytest.raises(OSError, match="character device"):
        write_atomically(link, lambda handle: handle.write(b"x"))
    assert os.path.islink(link) and stat.S_ISCHR(os.stat(DEV_FULL).st_mode)
    os.mkfifo(tmp_path / "fifo")
    with pytest.raises(OSError, match="is a FIFO"):  # the writer itself refuses special files ...
        write_atomically(tmp_path / "fifo", lambda handle: handle.write(b"x"))
    one_line_exit_2(
        ["fuse", str(posed_file), "-o", str(DEV_FULL)],
        capsys,  # ... so this cannot replace the device
        "-o /dev/full: is a character device",
    )
    assert stat.S_ISCHR(os.stat(DEV_FULL).st_mode)


@pytest.mark.parametrize("stdout_to", ["a file", "a pipe"])
def test_standard_output_is_no_output_path(posed_file, tmp_path, stdout_to):
    """A new user's probe: `fuse -o /dev/stdout` with standard output on a pipe said "folder /proc/PID/fd takes no
    new file"; with it redirected to a file, the map went into that file, the terminal's log. A link that passes
    through /dev or /proc (/dev/stdout, /proc/self/fd/1, a link of one's own to them) names no file to write:
    refused in one sentence, nothing written."""
    link = tmp_path / "out.npz"
    link.symlink_to("/dev/stdout")
    for path in ("/dev/stdout", "/proc/self/fd/1", str(link)):
        command = [sys.executable, "-m", "services.cli", "fuse", str(posed_file), "-o", path]
        if stdout_to == "a file":
            with open(tmp_path / "stdout", "wb") as out:
                result = subprocess.run(
                    command, stdout=out, stderr=subprocess.PIPE, text=True, timeout=120, check=False
                )
            written = (tmp_path / "stdout").read_bytes()
        else:
            result = subprocess.run(command, capture_output=True, text=True, timeout=120, check=False)
            written = result.stdout.encode()
        assert result.returncode == 2 and written == b"", (path, result.stderr)
        assert "which holds devices and process entries, not files" in result.stderr, result.stderr
        assert result.stderr.count("\n") == 1
    assert os.path.islink(link)


def test_a_file_of_another_kind_is_not_replaced(posed_file, tmp_path, capsys):
    """A new user's probe: `fuse -o keep.png` turned a PNG into a map, `calibrate -o map.npz` a map into JSON, exit 0
    (`export` refused a name of the other format). An output that would replace a file of another kind than it
    writes is refused; a file of its kind, or an empty one, is replaced."""
    png = tmp_path / "keep.png"
    png.write_bytes(b"\x89PNG\r\n\x1a\n" + bytes(32))
    one_line_exit_2(["fuse", str(posed_file), "-o", str(png)], capsys, "the file there is not a map")
    assert png.read_bytes().startswith(b"\x89PNG")
    assert main(["fuse", str(posed_file), "-o", str(tmp_path / "a.npz")]) == 0
    assert main(["fuse", str(posed_file), "-o", str(tmp_path / "a.npz")]) == 0  # (a map replaces a map)
    (tmp_path / "empty").write_bytes(b"")
    assert main(["fuse", str(posed_file), "-o", str(tmp_path / "empty")]) == 0
    with pytest.raises(UsageError, match="is not a JSON object"):
        refuse_another_kind(tmp_path / "a.npz", "json", "-o")
    (tmp_path / "c.json").write_text(' {"a": 1}')
    refuse_another_kind(tmp_path / "c.json", "json", "-o")


def test_an_archive_of_another_kind_is_not_replaced(posed_file, tmp_path, capsys):
    """A new user's probe: `fuse -o sim/truth.npz` replaced the simulator's truth raster with a map, exit 0 (any
    .npz was taken as replaceable). A map replaces a map and poses replace poses; a truth raster, a posed-scan file
    under a map, a map under poses or another program's archive is refused and kept."""
    import numpy as np

    truth, foreign, poses = tmp_path / "truth.npz", tmp_path / "foreign.npz", tmp_path / "poses.npz"
    np.savez(truth, occupied=np.zeros((2, 2), bool), visible=np.ones((2, 2), bool))
    np.savez(foreign, data=np.arange(3))
    poses.write_bytes(posed_file.read_bytes())
    for path in (truth, foreign, poses):
        kept = path.read_bytes()
        one_line_exit_2(["fuse", str(posed_file), "-o", str(path)], capsys, "the file there is not a map")
        assert path.read_bytes() == kept
    assert main(["fuse", str(posed_file), "-o", str(tmp_path / "map.npz")]) == 0
    with pytest.raises(UsageError, match="not a posed-scan or pose-distribution file"):
        refuse_another_kind(tmp_path / "map.npz", "poses", "-o")
    refuse_another_kind(poses, "poses", "-o")  # (poses replace poses)
    np.savez(tmp_path / "none.npz")  # an empty archive
    refuse_another_kind(tmp_path / "none.npz", "map", "-o")


def _an_old_archive() -> bytes:
    """The bytes of a small .npz archive of an earlier map (an output of the kind `fuse` replaces)."""
    import io

    import numpy as np

    buffer = io.BytesIO()
    np.savez(buffer, logodds=np.zeros(3))
    return buffer.getvalue()


def test_a_symlink_is_written_through_and_stays_a_link(posed_file, tmp_path, capsys):
    target = tmp_path / "maps" / "real.npz"
    target.parent.mkdir()
    target.write_bytes(_an_old_archive())
    os.chmod(target, 0o640)
    link = tmp_path / "map.npz"
    link.symlink_to(target)
    assert main(["fuse", str(posed_file), "-o", str(link)]) == 0
    assert f"wrote {link}" in capsys.readouterr().out
    assert os.path.islink(link) and os.readlink(link) == str(target)
    assert load_map(target).observed.any()
    assert stat.S_IMODE(os.stat(target).st_mode) == 0o640  # the replaced file keeps its permissions
    dangling = tmp_path / "new.npz"
    dangling.symlink_to(tmp_path / "maps" / "created.npz")
    assert main(["fuse", str(posed_file), "-o", str(dangling)]) == 0
    assert os.path.islink(dangling) and load_map(tmp_path / "maps" / "created.npz").observed.any()
    assert sorted(p.name for p in (tmp_path / "maps").iterdir()) == ["created.npz", "real.npz"]


def test_a_failed_write_is_an_error_not_wrote_and_keeps_the_old_file(posed_file, tmp_path, capsys, monkeypatch):
    out = tmp_path / "map.npz"
    out.write_bytes(previous := _an_old_archive())

    def failing_fsync(descriptor: int) -> None:
        raise OSError(errno.EIO, os.strerror(errno.EIO))

    monkeypatch.setattr(os, "fsync", failing_fsync)
    assert main(["fuse", str(posed_file), "-o", str(out)]) == 2
    captured = capsys.readouterr()
    last = captured.err.strip().splitlines()[-1]  # after the progress bar
    assert last == f"posegrid fuse: error: {os.strerror(errno.EIO)} ({out})", captured.err
    assert "wrote" not in captured.out + captured.err and "Traceback" not in captured.err
    assert out.read_bytes() == previous
    assert sorted(p.name for p in tmp_path.iterdir()) == ["map.npz"]  # no temporary file left


def test_disk_full_midway_leaves_the_old_file_and_no_temporary(tmp_path):
    out = tmp_path / "out.json"
    out.write_text("old")

    def fails_halfway(handle) -> None:
        handle.write(b"half")
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    with pytest.raises(OSError, match=os.strerror(errno.ENOSPC)) as failure:
        write_atomically(out, fails_halfway)
    assert failure.value.filename == str(out)
    assert out.read_text() == "old" and sorted(p.name for p in tmp_path.iterdir()) == ["out.json"]


@pytest.mark.skipif(os.geteuid() == 0, reason="root writes into any folder")
def test_an_unwritable_folder_is_refused(tmp_path):
    folder = tmp_path / "locked"
    folder.mkdir()
    folder.chmod(0o500)
    try:
        assert "cannot be written" in output_path_problem(folder / "out.npz")
    finally:
        folder.chmod(0o700)


@pytest.mark.parametrize("unnamed", [True, False], ids=["O_TMPFILE", "named trial"])
def test_the_folder_is_tried_with_a_file_that_leaves_nothing(tmp_path, monkeypatch, unnamed):
    """A folder whose permissions pass but whose file system makes no file (/proc; /sys for root) is refused up
    front; a disk's folder is tried with a file that leaves nothing behind, unnamed where the system has
    O_TMPFILE, else named and removed."""
    if not unnamed:
        monkeypatch.delattr(os, "O_TMPFILE", raising=False)
    assert output_path_problem(tmp_path / "out.npz") is None
    assert list(tmp_path.iterdir()) == []
    problem = output_path_problem("/proc/posegrid-out.npz")
    assert problem is not None and problem.startswith("folder /proc ")
    if os.geteuid() == 0:  # root passes the permissions: the trial file is what refuses
        assert "takes no new file" in problem


def unusable_ranges(tmp_path: Path, scans: slice, value: float = -1.0) -> Path:
    """The room's posed scans with every range of ``scans`` set to ``value`` m, negative or below range_min
    (0.05 m): no usable beam in those scans."""
    posed = room_posed_scans(steps=6, beams=90)
    ranges = posed.ranges.copy()
    ranges[scans] = value
    path = tmp_path / "unusable.npz"
    save_posed_scans(path, replace(posed, ranges=ranges))
    return path


@pytest.mark.parametrize("grid", ["regular", "adaptive"])
def test_scans_without_a_usable_beam_give_no_empty_map(tmp_path, capsys, grid):
    out = tmp_path / "map.npz"
    posed = unusable_ranges(tmp_path, slice(None))
    one_line_exit_2(
        ["fuse", str(posed), "-o", str(out), "--grid", grid],
        capsys,
        "none of its 6 scans has a usable beam",
        "nothing written",
    )
    assert not out.exists()
    partly = unusable_ranges(tmp_path, slice(1, 3))
    assert main(["fuse", str(partly), "-o", str(out), "--grid", grid]) == 0
    said = capsys.readouterr().out
    assert "4 scans fused" in said and "2 without a usable beam" in said, said
    assert load_map(out).observed.any()


@pytest.mark.slow
def test_run_exports_no_empty_map(tmp_path):
    """`posegrid run --export` of scans without a usable beam: exit 1, an error line, no file."""
    posed = unusable_ranges(tmp_path, slice(None), 0.01)  # (a LaserScan message carries no negative range)
    out = tmp_path / "run.npz"
    process = subprocess.Popen(
        [sys.executable, "-m", "services", "run", "--posed", str(posed), "--no-api", "--export", str(out)],
        cwd=ROOT,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,
    )
    try:
        _, err = process.communicate(timeout=180)
    finally:
        if process.poll() is None:
            os.killpg(process.pid, signal.SIGKILL)  # the launcher's own group, started above
            process.wait()
    assert process.returncode == 1, err
    assert "the map is empty" in err and f"nothing written to {out}" in err
    assert not out.exists() and not list(tmp_path.glob(".*partial"))


class AssembledMap:
    """Stands in for services.map_client.MapReader at the end of a run: the shards' map, already assembled."""

    def __init__(self, grid) -> None:
        self.grid = grid

    def assemble(self, shards: int, resolution: float):
        return self.grid


def test_run_export_that_cannot_be_written_is_an_error_not_wrote(posed_file, tmp_path, capsys):
    """The launcher's export goes through the same writer: a path that turned into a FIFO while the run went on
    (it was checked at the start) gives exit 1 and one error line, and the FIFO stays."""
    from schemas.files import load_posed_scans
    from services.fusion_runner import fuse_posed_scans
    from services.nodes.launcher import Plan, _export

    grid = fuse_posed_scans(load_posed_scans(posed_file))
    fifo = tmp_path / "map.npz"
    os.mkfifo(fifo)
    plan = Plan(map_name="main", robot="robot0", shards=1, resolution=0.05, mapper_argv=[], source_argv=[], export=fifo)
    assert _export(AssembledMap(grid), plan, 0, "") == 1
    captured = capsys.readouterr()
    assert (
        captured.err.strip()
        == f"posegrid run: error: cannot write {fifo}: is a FIFO, not a regular file; give the path of a regular file"
        and "wrote" not in captured.out
    )
    assert stat.S_ISFIFO(os.lstat(fifo).st_mode) and sorted(p.name for p in tmp_path.iterdir()) == ["map.npz"]
    plan.export = tmp_path / "written.npz"
    assert _export(AssembledMap(grid), plan, 0, "") == 0
    assert f"wrote {plan.export}" in capsys.readouterr().out and load_map(plan.export).observed.any()


@pytest.fixture(scope="module")
def sim_folder(tmp_path_factory) -> Path:
    """A simulator folder (`posegrid simulate`, 100 steps), the input of `slam` and `calibrate`."""
    folder = tmp_path_factory.mktemp("sim") / "sim"
    assert main(["simulate", str(folder), "--seed", "0", "--steps", "100"]) == 0
    return folder


@pytest.mark.parametrize(
    "command, replaced",
    [
        (lambda sim, posed: ["calibrate", str(sim), "-o", str(sim / "controls.npz")], "sim/controls.npz"),
        (lambda sim, posed: ["slam", str(sim), "--algo", "ekf", "-o", str(sim / "scans.npz")], "sim/scans.npz"),
        (lambda sim, posed: ["slam", str(sim), "--algo", "ekf", "-o", "link"], "sim/truth.npz"),
        (lambda sim, posed: ["fuse", str(posed), "-o", str(posed)], "room.npz"),
        (lambda sim, posed: ["fuse", str(posed), "-o", "link"], "room.npz"),
        # (a probe: `run --export` replaced the run's own input and exited 0)
        (lambda sim, posed: ["run", "--posed", str(posed), "--no-api", "--export", str(posed)], "room.npz"),
        (lambda sim, posed: ["run", "--sim-dir", str(sim), "--no-api", "--export", "link"], "sim/scans.npz"),
    ],
    ids=[
        "calibrate, a file of its folder",
        "slam, a file of its folder",
        "slam, a link to one",
        "fuse",
        "fuse, link",
        "run --posed",
        "run --sim-dir, link",
    ],
)
def test_an_output_that_would_replace_the_input_is_refused(
    tmp_path, monkeypatch, capsys, sim_folder, posed_file, command, replaced
):
    """An output path that is the input file, or a data file of the input folder, directly or through a link,
    is refused in one line, and the input is left as it was."""
    target = sim_folder.parent / replaced if replaced.startswith("sim/") else posed_file
    monkeypatch.chdir(tmp_path)
    (tmp_path / "link").symlink_to(target)
    before = target.read_bytes()
    one_line_exit_2(command(sim_folder, posed_file), capsys, "is a file this command reads", "give another path")
    assert target.read_bytes() == before


def test_an_output_beside_the_inputs_of_a_folder_is_written(tmp_path, sim_folder):
    """A new file inside the input folder is no input: `slam` writes its poses there."""
    output = sim_folder / "poses.npz"
    assert main(["slam", str(sim_folder), "--algo", "ekf", "-o", str(output)]) == 0
    assert output.is_file()
    output.unlink()


def test_a_pgm_export_whose_yaml_would_replace_the_map_is_refused(tmp_path, posed_file, capsys):
    """The map_server YAML goes beside the pgm as NAME.yaml: a map file named m.yaml was replaced by it."""
    map_path = tmp_path / "m.yaml"  # a map file with an unusual name (load_map reads the content, not the name)
    assert main(["fuse", str(posed_file), "-o", str(map_path)]) == 0
    capsys.readouterr()
    before = map_path.read_bytes()
    one_line_exit_2(
        ["export", str(map_path), "--format", "pgm", "-o", str(tmp_path / "m.pgm")],
        capsys,
        "the map_server YAML beside -o,",
        "is a file this command reads",
    )
    assert map_path.read_bytes() == before and not (tmp_path / "m.pgm").exists()


def test_a_reader_that_stopped_reading_is_one_line_without_empty_brackets(sim_folder, tmp_path):
    """A new user's probe: `posegrid eval ... | true` said "error: Broken pipe ()" (and a standard output on a full
    disk "No space left on device ()": an error that names no file now names none). A pipe whose reader has gone,
    as from a shell, gives one line and exit 2."""
    read_end, write_end = os.pipe()
    os.close(read_end)  # (the reader gone before anything is written)
    try:
        result = subprocess.run(
            [sys.executable, "-m", "services", "eval-traj", str(sim_folder / "groundtruth.npz"), str(sim_folder)],
            stdout=write_end,
            stderr=subprocess.PIPE,
            text=True,
            timeout=120,
            check=False,
        )
    finally:
        os.close(write_end)
    assert result.returncode == 2, result.stderr
    assert result.stderr.strip() == "posegrid eval-traj: error: its output's reader stopped reading (broken pipe)"
