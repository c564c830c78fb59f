"""The layering rules of docs/architecture.md, checked on the source."""

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
FORBIDDEN = {
    "mapping": {"slam", "schemas", "services", "zenoh", "fastapi", "uvicorn", "socket", "subprocess"},
    "slam": {"schemas", "services", "zenoh", "fastapi", "uvicorn", "socket", "subprocess"},
    "schemas": {"mapping", "slam", "services", "zenoh", "fastapi", "uvicorn"},
}


def imported_roots(path: Path) -> set[str]:
    roots = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            roots.update(alias.name.split(".")[0] for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            roots.add(node.module.split(".")[0])
    return roots


@pytest.mark.parametrize("package", sorted(FORBIDDEN))
def test_package_imports_only_what_its_layer_allows(package):
    files = sorted((ROOT / package).rglob("*.py"))
    assert files, f"{package}/ has no modules"
    offenders = {str(f.relative_to(ROOT)): sorted(imported_roots(f) & FORBIDDEN[package]) for f in files}
    assert not {f: bad for f, bad in offenders.items() if bad}


def imported_modules(path: Path) -> set[str]:
    """Every module ``path`` imports, absolute names (lazy imports inside functions included)."""
    names = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            names.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            names.add(node.module)
            names.update(f"{node.module}.{alias.name}" for alias in node.names)
    return names


def test_no_runtime_module_imports_the_command_line():
    """services/ below the CLI (state, nodes, api and the shared modules) never reaches services.cli or
    services.commands: a process depends on what it runs, not on argparse glue."""
    cli = {ROOT / "services" / "cli.py", ROOT / "services" / "__main__.py"}
    runtime = [
        f
        for f in sorted((ROOT / "services").rglob("*.py"))
        if f not in cli and "commands" not in f.relative_to(ROOT).parts
    ]
    offenders = {
        str(f.relative_to(ROOT)): sorted(
            m for m in imported_modules(f) if m == "services.cli" or m.startswith("services.commands")
        )
        for f in runtime
    }
    assert not {f: bad for f, bad in offenders.items() if bad}


def test_the_state_package_holds_no_networking():
    """services/state is what a shard and a SLAM node decide, testable without a network."""
    forbidden = {"zenoh", "fastapi", "uvicorn", "socket", "subprocess"}
    offenders = {
        str(f.relative_to(ROOT)): sorted(imported_roots(f) & forbidden)
        for f in sorted((ROOT / "services" / "state").rglob("*.py"))
    }
    assert offenders and not {f: bad for f, bad in offenders.items() if bad}
