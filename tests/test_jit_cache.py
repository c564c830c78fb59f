"""mapping.jit.kernel: numba's disk cache never serves a kernel compiled against an older helper.

A tiny package in a temporary directory (kernel -> helper -> constants, as mapping's kernels inline
raytrace and window_walk) runs in fresh processes that share one NUMBA_CACHE_DIR; between runs a helper or
a constant changes. numba's plain ``njit(cache=True)`` is the control: it loads the stale machine code.
"""

import ast
import os
import subprocess
import sys
import time
import warnings
from pathlib import Path

import pytest

from mapping.jit import closure_files, kernel

ROOT = Path(__file__).resolve().parents[1]

#: what run(2.0) returns: gain(x) + 1 with gain(x) = GAIN * x and GAIN = 3
FIRST = 7.0


def decorator(flavour: str, options: str) -> str:
    """The decorator line of one kernel: mapping.jit's, or numba's own cache (the control)."""
    if flavour == "kernel":
        return f"@kernel({options})"
    return f"@numba.njit({', '.join(filter(None, ['cache=True', options]))})"


def write_package(root: Path, flavour: str) -> Path:
    """tinypkg/: kernel.run inlines helper.gain, which reads consts.GAIN through a relative import."""
    header = "from mapping.jit import kernel\n" if flavour == "kernel" else "import numba\n"
    package = root / "tinypkg"
    package.mkdir()
    (package / "__init__.py").write_text("")
    (package / "consts.py").write_text("GAIN = 3.0\n")
    inlined, plain = decorator(flavour, 'inline="always"'), decorator(flavour, "")
    (package / "helper.py").write_text(
        f"{header}from .consts import GAIN\n\n\n{inlined}\ndef gain(x):\n    return GAIN * x\n"
    )
    (package / "kernel.py").write_text(
        f"{header}from tinypkg.helper import gain\n\n\n{plain}\ndef run(x):\n    return gain(x) + 1.0\n"
    )
    return package


def package_env(root: Path) -> dict[str, str]:
    """The environment of a fresh process that imports the packages written under ``root``, its numba cache there."""
    return {
        **os.environ,
        "NUMBA_CACHE_DIR": str(root / "numba_cache"),
        "PYTHONDONTWRITEBYTECODE": "1",
        "PYTHONPATH": os.pathsep.join([str(root), str(ROOT)]),
    }


def run_python(root: Path, script: str) -> str:
    """``script`` in a fresh process that imports tinypkg from ``root``, the numba cache under it: stdout."""
    done = subprocess.run(
        [sys.executable, "-c", script],
        cwd=root,
        env=package_env(root),
        capture_output=True,
        text=True,
        timeout=300,
        check=False,
    )
    assert done.returncode == 0, done.stderr
    return done.stdout


def run_kernel(root: Path) -> tuple[float, int, int]:
    """run(2.0) in a fresh process: (result, cache hits, cache misses)."""
    script = (
        "from tinypkg.kernel import run\nv = run(2.0)\n"
        "print(v, sum(run.stats.cache_hits.values()), sum(run.stats.cache_misses.values()))"
    )
    value, hits, misses = run_python(root, script).split()
    return float(value), int(hits), int(misses)


EDITS = {
    # the constant two imports away: GAIN = 30 -> 30 * 2 + 1
    "consts": ("consts.py", "GAIN = 3.0", "GAIN = 30.0", 61.0),
    # the inlined helper's body: 3 * 2 * 2 + 1
    "helper": ("helper.py", "return GAIN * x", "return GAIN * x * x", 13.0),
}


@pytest.mark.parametrize("edit", sorted(EDITS))
def test_an_edit_behind_a_cached_kernel_recompiles_it(tmp_path, edit):
    package = write_package(tmp_path, "kernel")
    assert run_kernel(tmp_path) == (FIRST, 0, 1)
    assert run_kernel(tmp_path) == (FIRST, 1, 0), "an unchanged kernel comes from the disk cache"
    name, old, new, expected = EDITS[edit]
    (package / name).write_text((package / name).read_text().replace(old, new))
    assert run_kernel(tmp_path) == (expected, 0, 1)


def test_numbas_own_cache_serves_the_stale_helper(tmp_path):
    """The control: with njit(cache=True) the same edit goes unnoticed."""
    package = write_package(tmp_path, "numba")
    assert run_kernel(tmp_path) == (FIRST, 0, 1)
    name, old, new, _ = EDITS["consts"]
    (package / name).write_text((package / name).read_text().replace(old, new))
    assert run_kernel(tmp_path) == (FIRST, 1, 0)


def test_without_numbas_caching_internals_kernels_run_uncached_with_a_warning(tmp_path):
    """A numba whose private caching classes moved: correct results, no disk cache, one warning."""
    write_package(tmp_path, "kernel")
    script = (
        "import warnings\nfrom numba.core import caching\ndel caching.FunctionCache._impl_class\n"
        "with warnings.catch_warnings(record=True) as caught:\n    warnings.simplefilter('always')\n"
        "    from tinypkg.kernel import run\n"
        "print(run(2.0), *sorted({str(w.message).split(': ')[1] for w in caught}), sep='\\n')"
    )
    value, *messages = run_python(tmp_path, script).splitlines()
    assert float(value) == FIRST
    expected = (
        "its caching internals are not as mapping.jit expects (CacheImpl.locator is not a property); "
        "kernels compile without a disk cache"
    )
    assert messages == [expected]
    assert not list((tmp_path / "numba_cache").rglob("*.nbi"))


def test_a_kernel_with_no_writable_cache_folder_compiles_in_each_process(tmp_path):
    """A probe: posegrid installed read-only with an unwritable HOME: numba raised "cannot cache function ...: no
    locator available" on the decorator, and `posegrid fuse` failed with a traceback. The kernel now compiles
    without a disk cache and says where to put one. (Here: the package's __pycache__ a file, NUMBA_CACHE_DIR and the
    user cache inside a file: numba's places, none writable, as root.)"""
    write_package(tmp_path, "kernel")
    for blocked in (tmp_path / "tinypkg" / "__pycache__", tmp_path / "blocked"):
        blocked.write_text("a file where numba wants a folder")
    done = subprocess.run(
        [sys.executable, "-c", "from tinypkg.kernel import run\nprint(run(2.0))"],
        cwd=tmp_path,
        env={
            **package_env(tmp_path),
            "NUMBA_CACHE_DIR": str(tmp_path / "blocked" / "cache"),
            "XDG_CACHE_HOME": str(tmp_path / "blocked" / "user"),  # (numba's user-wide cache)
        },
        capture_output=True,
        text=True,
        timeout=300,
        check=False,
    )
    assert done.returncode == 0 and float(done.stdout) == FIRST, done.stderr
    assert "numba finds no writable folder to cache compiled kernels in" in done.stderr, done.stderr
    assert "NUMBA_CACHE_DIR" in done.stderr and "Traceback" not in done.stderr, done.stderr


def test_the_closure_of_a_fusion_kernel_holds_the_helpers_it_inlines():
    files = closure_files("mapping.samples_pass", ROOT / "mapping" / "samples_pass.py")
    assert {
        "mapping/raytrace.py",
        "mapping/window_walk.py",
        "mapping/free_runs.py",
        "mapping/beam_model.py",
        "mapping/samples_pass.py",
    } <= set(files)
    assert all(path.startswith(("mapping/", "slam/")) for path in files), "numpy and numba stay outside"


def test_the_closure_does_not_follow_packages_installed_beside_the_project(tmp_path):
    """A probe installed posegrid with pip: the import root was site-packages, and each kernel module's closure parsed
    615 files (numba, numpy, setuptools, ...), 12.6 s at every process's start; `posegrid run` then failed to open
    its sessions on a loaded machine. Only the project's packages (and the kernel's own) are followed."""
    site = tmp_path / "site-packages"
    for name, text in {
        "mapping/__init__.py": "",
        "mapping/kern.py": "import numbaish\nfrom mapping import helper\nfrom slam import other\n",
        "mapping/helper.py": "from numbaish.core import deep\n",
        "slam/__init__.py": "",
        "slam/other.py": "",
        "numbaish/__init__.py": "from numbaish import core\n",
        "numbaish/core.py": "",
    }.items():
        (site / name).parent.mkdir(parents=True, exist_ok=True)
        (site / name).write_text(text)
    files = closure_files("mapping.kern", site / "mapping" / "kern.py")
    assert set(files) == {
        "mapping/__init__.py",
        "mapping/kern.py",
        "mapping/helper.py",
        "slam/__init__.py",
        "slam/other.py",
    }, files


def numba_cache_calls(path: Path) -> list[int]:
    """Lines of calls with cache=True (numba's own cache) in one source file."""
    return [
        node.lineno
        for node in ast.walk(ast.parse(path.read_text(), str(path)))
        if isinstance(node, ast.Call)
        and any(k.arg == "cache" and isinstance(k.value, ast.Constant) and k.value.value is True for k in node.keywords)
    ]


def test_no_kernel_uses_numbas_own_cache():
    files = [f for package in ("mapping", "slam", "bench") for f in sorted((ROOT / package).rglob("*.py"))]
    offenders = {str(f.relative_to(ROOT)): numba_cache_calls(f) for f in files}
    assert not {f: lines for f, lines in offenders.items() if lines}


def test_a_kernel_without_reference_counting_writes_arrays_and_refuses_to_create_one(tmp_path):
    """refcounted=False: the kernel reads and writes the arrays it is handed (in tuples too); one that would create
    an array does not compile."""
    package = tmp_path / "nrtpkg"
    package.mkdir()
    (package / "__init__.py").write_text("")
    (package / "kernels.py").write_text(
        "import numpy as np\nfrom mapping.jit import kernel\n\n\n@kernel(refcounted=False)\ndef add(pair):\n"
        "    a, b = pair\n    for i in range(a.shape[0]):\n        a[i] += b[i]\n\n\n"
        "@kernel(refcounted=False)\ndef make(n):\n    return np.zeros(n)\n"
    )
    script = (
        "import numpy as np\nfrom numba.core.errors import TypingError\nfrom nrtpkg.kernels import add, make\n"
        "a = np.zeros(3)\nadd((a, np.arange(3.0)))\nprint(a.tolist())\n"
        "try:\n    make(3)\nexcept TypingError:\n    print('refused')\n"
    )
    assert run_python(tmp_path, script).split("\n")[:2] == ["[0.0, 1.0, 2.0]", "refused"]


def test_kernel_refuses_a_cache_option():
    with pytest.raises(TypeError, match="always caches"):
        kernel(cache=False)


def _python(root: Path, script: str) -> subprocess.Popen:
    """``script`` started in a fresh process as :func:`run_python` runs it, its stdin and stdout piped."""
    return subprocess.Popen(
        [sys.executable, "-c", script],
        cwd=root,
        env=package_env(root),
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )


def test_a_kernel_another_process_is_compiling_is_loaded_from_the_cache_not_compiled_again(tmp_path):
    """Two processes start on a fresh cache: the one holding the kernel's compile lock compiles it; the other, which
    called the kernel before the first had saved it, waits for the lock and loads it (a cache hit, no compile). The
    first compiles only after the second has called the kernel (and half a second more), so without the lock the
    second would have found no cache entry and compiled its own."""
    write_package(tmp_path, "kernel")
    counts = "print(v, sum(run.stats.cache_hits.values()), sum(run.stats.cache_misses.values()), flush=True)\n"
    holder = _python(
        tmp_path,
        "import sys\nfrom tinypkg.kernel import run\nfrom mapping.jit import _compiling, _lock_path\n"
        "with _compiling(_lock_path(run._cache)):\n    print('holding', flush=True)\n    sys.stdin.readline()\n"
        "    v = run(2.0)\n" + counts,
    )
    waiter = None
    try:
        assert holder.stdout is not None and holder.stdin is not None
        assert holder.stdout.readline().strip() == "holding", holder.stderr
        calling = "from tinypkg.kernel import run\nprint('calling', flush=True)\nv = run(2.0)\n"
        waiter = _python(tmp_path, calling + counts)
        assert waiter.stdout is not None
        assert waiter.stdout.readline().strip() == "calling"
        time.sleep(0.5)
        holder.stdin.write("go\n")
        holder.stdin.flush()
        held, _ = holder.communicate(timeout=300)
        waited, _ = waiter.communicate(timeout=300)
    finally:
        for process in (holder, waiter):
            if process is not None and process.poll() is None:
                process.kill()
                process.wait()
    assert held.split() == [str(FIRST), "0", "1"]
    assert waited.split() == [str(FIRST), "1", "0"]


def test_a_compile_lock_held_too_long_is_passed_by_with_a_warning(tmp_path, monkeypatch):
    """A process that holds a kernel's lock past COMPILE_WAIT (hung, stopped) does not stop the others: they compile
    without it and say so."""
    import fcntl

    import mapping.jit as jit

    monkeypatch.setattr(jit, "COMPILE_WAIT", 0.2)
    path = tmp_path / "k.lock"
    holder = os.open(path, os.O_RDWR | os.O_CREAT)
    try:
        fcntl.flock(holder, fcntl.LOCK_EX)
        with pytest.warns(RuntimeWarning, match="compiling without waiting for it"), jit._compiling(str(path)):
            assert str(path) in jit._HELD  # (compiled as if held: a nested compile does not wait again)
    finally:
        os.close(holder)
    assert str(path) not in jit._HELD
    other = os.open(path, os.O_RDWR)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            # free again: taken at once, and held while the body runs
            with jit._compiling(str(path)), pytest.raises(BlockingIOError):
                fcntl.flock(other, fcntl.LOCK_EX | fcntl.LOCK_NB)
        fcntl.flock(other, fcntl.LOCK_EX | fcntl.LOCK_NB)  # released after it
    finally:
        os.close(other)
