"""``io`` reads and writes files only: it imports neither the evaluation, the mesh extraction nor
plotting, not even inside functions (the layering of docs/architecture.md)."""

from __future__ import annotations

import ast
from pathlib import Path

import neb_slam_core.io

FORBIDDEN = ("neb_slam_core.eval", "neb_slam_core.mesh", "matplotlib")


def imported_modules(path: Path) -> set[str]:
    """Absolute names of every module ``path`` imports (relative imports resolved in ``neb_slam_core.io``)."""
    names = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            names.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = ["neb_slam_core", "io"][: 3 - node.level] if node.level else []
            module = ".".join(base + ([node.module] if node.module else []))
            names.add(module)
            names.update(f"{module}.{alias.name}" for alias in node.names)
    return names


def test_io_imports_no_evaluation_mesh_or_plotting():
    files = sorted(Path(neb_slam_core.io.__file__).parent.glob("*.py"))
    assert any(f.name == "run_dir.py" for f in files)
    for path in files:
        bad = sorted(n for n in imported_modules(path) if n.startswith(FORBIDDEN))
        assert not bad, f"{path.name} imports {bad}"


def test_relative_imports_resolve_to_the_package():
    src = Path(neb_slam_core.io.__file__).parent / "run_dir.py"
    names = imported_modules(src)
    assert "neb_slam_core.io.trajectory" in names and "neb_slam_core.errors" in names
