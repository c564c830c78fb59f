"""numba kernels whose on-disk cache follows every source file they can inline.

numba's own cache (``njit(cache=True)``) stamps a kernel's compiled code with its own file only. A kernel inlines
helpers and freezes module constants from other files (``mapping.raytrace``, ``mapping.window_walk``, ...), so after
an edit there numba would go on loading the old machine code. :func:`kernel` is ``njit`` with a cache whose source
stamp also holds a SHA-256 over the kernel's import closure: its own file and every first-party module it imports,
followed transitively (imports read from the source, relative ones and those inside functions included). A
first-party module is one that lives under the same import root as the kernel's package (for ``mapping.fusion`` in
``/repo/mapping/fusion.py``: ``/repo``) and belongs to one of the project's packages (:data:`FIRST_PARTY`) or the
kernel's own; installed packages (numpy, numba) stay outside it, as with numba's own cache, also where posegrid
itself is installed beside them. An edit of any file in the closure makes every kernel that reaches it compile afresh
on its next call, and the fresh code replaces the stale entry in place.

The cache goes where numba's would (``NUMBA_CACHE_DIR`` if set, else the package's ``__pycache__``, else the
user cache), under the same file names. It builds on numba's private caching internals (the dispatcher's
``_cache``, ``FunctionCache._impl_class``, the impl's ``_locator`` behind its ``locator`` property, the
locators' ``get_source_stamp`` and ``_py_file``), checked against numba 0.59.1 and 0.68.1; where they are
missing, kernels compile without a disk cache (each process afresh), with a warning.

Processes that start together (the shards and the SLAM node of ``posegrid run``, the workers of the test suite)
would each compile the same kernel at once, minutes of CPU on a fresh install. A kernel compiles under a lock
file beside its cache entry (``<cache file>.lock``, ``flock``): the first process compiles and saves it, the
others wait and then load it from the cache (:func:`_compiling`).
"""

from __future__ import annotations

import ast
import contextlib
import functools
import hashlib
import os
import threading
import time
import warnings
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any, TypeVar

try:
    import fcntl

    _HAS_FLOCK = True
except ImportError:  # not POSIX: kernels compile without the lock between processes
    _HAS_FLOCK = False

import numba as nb

#: one import statement as read from a source file: (level of a relative import, module or "", names)
ImportRecord = tuple[int, str, tuple[str, ...]]


@functools.cache
def _read_source(path: str, mtime_ns: int, size: int) -> tuple[bytes, tuple[ImportRecord, ...]]:
    """The SHA-256 of a file's bytes and its import statements (stat fields only key the memo)."""
    data = Path(path).read_bytes()
    records: list[ImportRecord] = []
    for node in ast.walk(ast.parse(data, path)):
        if isinstance(node, ast.Import):
            records.extend((0, alias.name, ()) for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            records.append((node.level, node.module or "", tuple(alias.name for alias in node.names)))
    return hashlib.sha256(data).digest(), tuple(records)


def _source(path: Path) -> tuple[bytes, tuple[ImportRecord, ...]]:
    """:func:`_read_source` for the file as it is now."""
    st = path.stat()
    return _read_source(str(path), st.st_mtime_ns, st.st_size)


def _module_file(root: Path, name: str) -> Path | None:
    """The file of module ``name`` under ``root`` (a module or a package's ``__init__.py``), or None."""
    base = root.joinpath(*name.split("."))
    for candidate in (base.parent / f"{base.name}.py", base / "__init__.py"):
        if candidate.is_file():
            return candidate
    return None


def _absolute(importer: str, is_package: bool, level: int, module: str) -> str | None:
    """The absolute name of ``from <level dots><module> import ...`` written in module ``importer``."""
    if level == 0:
        return module or None
    package = importer if is_package else importer.rpartition(".")[0]
    parts = package.split(".") if package else []
    if level - 1 > len(parts):
        return None
    base = parts[: len(parts) - (level - 1)] + (module.split(".") if module else [])
    return ".".join(base) or None


def _imported_names(name: str, path: Path) -> set[str]:
    """Every module the file of module ``name`` may import: ``from a import b`` gives ``a`` and ``a.b``."""
    is_package = path.name == "__init__.py"
    names: set[str] = set()
    for level, module, aliases in _source(path)[1]:
        base = _absolute(name, is_package, level, module)
        if base is None:
            continue
        names.add(base)
        names.update(f"{base}.{alias}" for alias in aliases if alias != "*")
    return names


def _import_root(module: str, path: Path) -> tuple[Path, str]:
    """The directory ``module`` was imported from, and its name there (a script: its folder and stem)."""
    parts = module.split(".")
    depth = len(parts) - (0 if path.name == "__init__.py" else 1)
    root = path.parent
    for _ in range(depth):
        root = root.parent
    if module != "__main__" and _module_file(root, module) == path:
        return root, module
    return path.parent, path.stem


def closure_files(module: str, path: Path) -> dict[str, Path]:
    """The file of ``module`` at ``path`` and of every first-party module it imports, transitively, by
    path relative to the import root (POSIX separators). Found once per process and module (:func:`_closure`):
    the kernels of one module share it, and the code a process runs is the code it imported."""
    return dict(_closure(module, path.resolve()))


#: the project's own top-level packages (pyproject.toml's): with the kernel's own, the only ones a closure follows.
#: Under the import root lies everything installed beside them where posegrid is installed as a package
#: (site-packages: numba, numpy, setuptools, ...), and following those parsed 615 files a kernel module, 12.6 s at
#: each process's start, against 18 files in a checkout
FIRST_PARTY = frozenset({"mapping", "slam", "schemas", "services"})


@functools.cache
def _closure(module: str, path: Path) -> tuple[tuple[str, Path], ...]:
    """:func:`closure_files` as found, for a resolved ``path``."""
    root, name = _import_root(module, path)
    files = {name: _module_file(root, name) or path}
    followed = FIRST_PARTY | {name.split(".")[0]}
    pending = [name]
    while pending:
        current = pending.pop()
        for imported in _imported_names(current, files[current]):
            if imported.split(".")[0] not in followed:
                continue
            found = _module_file(root, imported) if imported not in files else None
            if found is not None:
                files[imported] = found
                pending.append(imported)
    return tuple((file.relative_to(root).as_posix(), file) for file in files.values())


def closure_digest(module: str, path: Path) -> str:
    """SHA-256 (hex) over :func:`closure_files`, names and contents: a change in any of them changes it."""
    digest = hashlib.sha256()
    for relative, file in sorted(closure_files(module, path).items()):
        digest.update(relative.encode() + b"\0" + _source(file)[0])
    return digest.hexdigest()


class _ClosureLocator:
    """One of numba's cache locators, with :func:`closure_digest` added to its source stamp."""

    def __init__(self, inner: Any, module: str) -> None:
        self._inner = inner
        self._closure_module = module

    def __getattr__(self, name: str) -> Any:
        return getattr(self._inner, name)

    def get_source_stamp(self) -> Any:
        """Picklable; a changed stamp makes numba drop the cache index and compile afresh."""
        stamp = self._inner.get_source_stamp()
        path = Path(getattr(self._inner, "_py_file", ""))
        if not path.is_file():  # an interactive prompt or a zip archive: numba's own stamp
            return stamp
        return stamp, closure_digest(self._closure_module, path)


class UnsupportedNumba(RuntimeError):
    """numba's private caching classes are not as this module expects."""


def _wrap_locator(impl: Any, py_func: Callable[..., Any]) -> None:
    """Replace the locator numba chose for ``py_func`` (any of its candidates, ``NUMBA_CACHE_LOCATOR_CLASSES``
    included) by the same wrapped in :class:`_ClosureLocator`."""
    inner = getattr(impl, "_locator", None)
    if inner is None or impl.locator is not inner:
        raise UnsupportedNumba("CacheImpl has no _locator behind its locator property")
    impl._locator = _ClosureLocator(inner, py_func.__module__ or "__main__")


def _closure_cache_class() -> type | None:
    """numba's ``FunctionCache`` whose locator is wrapped in :class:`_ClosureLocator`; None (with a warning)
    if numba's private caching classes are missing."""
    try:
        from numba.core import caching

        impl_base = caching.FunctionCache._impl_class
        if not isinstance(getattr(impl_base, "locator", None), property):
            raise UnsupportedNumba("CacheImpl.locator is not a property")
    except (ImportError, AttributeError, UnsupportedNumba) as exc:
        _warn_uncached(exc)
        return None

    def init(self: Any, py_func: Callable[..., Any]) -> None:
        impl_base.__init__(self, py_func)
        _wrap_locator(self, py_func)

    impl = type("ClosureCompileResultCacheImpl", (impl_base,), {"__init__": init})
    return type("ClosureFunctionCache", (caching.FunctionCache,), {"_impl_class": impl})


def _warn_uncached(reason: Exception) -> None:
    """Kernels still compile, each process afresh: slower starts, never stale code."""
    warnings.warn(
        f"numba {nb.__version__}: its caching internals are not as mapping.jit expects ({reason}); "
        "kernels compile without a disk cache",
        RuntimeWarning,
        stacklevel=3,
    )


def _warn_no_cache_folder(py_func: Callable[..., Any]) -> None:
    """A kernel with nowhere to keep its machine code (a read-only install, and no writable ~/.cache or
    NUMBA_CACHE_DIR): numba raised on the decorator, so importing any fusion module failed with a traceback. It
    compiles in each process instead, said once a source file (the warning names it)."""
    warnings.warn(
        f"numba finds no writable folder to cache compiled kernels in (beside {py_func.__code__.co_filename} or in "
        "the user cache): set NUMBA_CACHE_DIR to a writable folder; kernels compile in each process meanwhile",
        RuntimeWarning,
        stacklevel=4,
    )


_CACHE_CLASS = _closure_cache_class()


def _no_refcounts_option() -> dict[str, bool]:
    """numba's option that compiles a kernel without reference counting ({} with a warning where it is missing:
    such kernels then compile with it, slower, never wrong)."""
    from numba.core.cpu import CPUTargetOptions

    if hasattr(CPUTargetOptions, "_nrt"):
        return {"_nrt": False}
    warnings.warn(
        f"numba {nb.__version__} has no _nrt option: kernels compile with reference counting", RuntimeWarning, 2
    )
    return {}


_NO_REFCOUNTS = _no_refcounts_option()


#: a kernel's Python function; the dispatcher numba returns for it is typed as the function (same parameters)
KernelT = TypeVar("KernelT", bound=Callable[..., Any])


#: the longest a process waits (s) for another to compile a kernel before compiling it itself, with a warning
COMPILE_WAIT = 900.0

#: one kernel compiles at a time in a process (numba's own compiler lock does the same, inside this one); the lock
#: files this process holds, by path (a kernel compiled while another one compiles, as a helper: already held ones
#: are not taken again)
_COMPILING = threading.RLock()
_HELD: set[str] = set()


@contextlib.contextmanager
def _compiling(lock_path: str | None) -> Iterator[None]:
    """Hold the lock file ``lock_path`` (None: none) across a compile, so that another process compiling the same
    kernel finishes and saves it first (the compile then loads it from the cache). Locks are taken in the order
    the kernels call each other, which has no cycle, so two processes never wait on each other."""
    with _COMPILING:
        if lock_path is None or not _HAS_FLOCK or lock_path in _HELD:
            yield
            return
        try:
            descriptor = os.open(lock_path, os.O_RDWR | os.O_CREAT, 0o644)
        except OSError:  # a cache folder that cannot be written: numba would not save there either
            yield
            return
        try:
            _wait_for_lock(descriptor, lock_path)
            _HELD.add(lock_path)
            try:
                yield
            finally:
                _HELD.discard(lock_path)
        finally:
            os.close(descriptor)  # (releases the lock)


def _wait_for_lock(descriptor: int, lock_path: str) -> None:
    """Take the exclusive lock on ``descriptor``, waiting up to COMPILE_WAIT s; past that, go on without it."""
    deadline = time.monotonic() + COMPILE_WAIT
    while True:
        try:
            fcntl.flock(descriptor, fcntl.LOCK_EX | fcntl.LOCK_NB)
            return
        except BlockingIOError:
            if time.monotonic() > deadline:
                warnings.warn(
                    f"another process has held {lock_path} for {COMPILE_WAIT:.0f} s: compiling without waiting for it",
                    RuntimeWarning,
                    stacklevel=4,
                )
                return
            time.sleep(0.05)


def _lock_path(cache: Any) -> str | None:
    """The lock file beside a kernel's cache index (numba's ``Cache``: ``_cache_path`` and its impl's
    ``filename_base``), None where numba lacks them."""
    folder = getattr(cache, "_cache_path", None)
    base = getattr(getattr(cache, "_impl", None), "filename_base", None)
    if not isinstance(folder, str) or not isinstance(base, str):
        return None
    with contextlib.suppress(OSError):
        os.makedirs(folder, exist_ok=True)
    return os.path.join(folder, f"{base}.lock")


def _compile_under_lock(dispatcher: Any, lock_path: str | None) -> None:
    """Route the dispatcher's compiles (a call with new argument types, or a kernel typing a call to it) through
    :func:`_compiling`."""
    compile_one = dispatcher.compile

    def compile_locked(sig: Any) -> Any:
        with _compiling(lock_path):
            return compile_one(sig)

    dispatcher.compile = compile_locked


def kernel(*, refcounted: bool = True, **options: Any) -> Callable[[KernelT], KernelT]:
    """``numba.njit(**options)`` with an on-disk cache keyed by the kernel's import closure.

    Use as ``@kernel(nogil=True, error_model="numpy")``; ``cache`` is not an option (always on).

    ``refcounted=False`` compiles the kernel, and the helpers it inlines, without numba's reference counting of
    arrays (numba's private ``_nrt`` option, off; where a numba lacks it, with reference counting and a warning):
    such a kernel may not create or return arrays, only read and write those it is handed, which its caller keeps
    alive. With reference counting, every array taken out of a tuple, or handed to an inlined helper, inside a
    loop may cost an atomic increment and decrement per iteration where numba's pruning of them fails (an array
    used in one branch only), which made a pass whose walk hands tuples of scratch arrays to its visitors several
    times slower.
    """
    if "cache" in options:
        raise TypeError("kernel() always caches; drop the cache option")
    if not refcounted:
        options.update(_NO_REFCOUNTS)

    def decorate(py_func: KernelT) -> KernelT:
        dispatcher = nb.njit(**options)(py_func)
        if _CACHE_CLASS is None:
            return dispatcher
        if not hasattr(dispatcher, "_cache"):
            _warn_uncached(UnsupportedNumba("the dispatcher has no _cache"))
            return dispatcher
        try:
            dispatcher._cache = _CACHE_CLASS(py_func)
        except UnsupportedNumba as exc:
            _warn_uncached(exc)
            return dispatcher
        except RuntimeError as exc:  # numba's "cannot cache function ...: no locator available for file ..."
            if "no locator" not in str(exc):
                raise
            _warn_no_cache_folder(py_func)
            return dispatcher
        _compile_under_lock(dispatcher, _lock_path(dispatcher._cache))
        return dispatcher

    return decorate
