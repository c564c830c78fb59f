"""The install's warm-up of the numba kernels (services/commands/warm_kernels.py; `make install` runs it on every
fresh clone, which is what checks the whole of it)."""

import pytest

from services.commands.warm_kernels import _cli


def test_a_warm_up_command_that_fails_names_itself_and_its_error(tmp_path):
    """A warm-up step that fails stops the install with the command and what it printed, not a bare exit code."""
    with pytest.raises(RuntimeError, match=r"posegrid fuse .*absent\.npz -o .* exited 2: .*no such file"):
        _cli("fuse", str(tmp_path / "absent.npz"), "-o", str(tmp_path / "m.npz"))
    assert not (tmp_path / "m.npz").exists()


def test_a_warm_up_command_that_works_prints_nothing(tmp_path, capsys):
    _cli("simulate", str(tmp_path / "sim"), "--steps", "5")
    assert capsys.readouterr() == ("", "") and (tmp_path / "sim" / "scans.npz").is_file()
