"""The benchmarks stay beside the product: no module of a runtime package imports `area3d_bench`
or names it (at module level, inside a function, through importlib or `python -m`); the `area3d`
command finds `area3d bench` through an installed entry point instead."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
RUNTIME_PACKAGES = (
    "area3d_msgs_py", "sim_bridge", "area3d_perception", "area3d_semantics", "area3d_planner",
    "area3d_bringup", "area3d_eval",
)  # fmt: skip
BENCH = "area3d_bench"


def bench_references(source: str) -> list[str]:
    """What in a module's source imports or names the benchmark package: `import` and
    `from ... import` statements anywhere, and string constants (importlib.import_module,
    `python -m`, an entry point's value)."""
    found = []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Import):
            found += [f"import {a.name}" for a in node.names if a.name.split(".")[0] == BENCH]
        elif isinstance(node, ast.ImportFrom) and (node.module or "").split(".")[0] == BENCH:
            found.append(f"from {node.module} import ...")
        elif isinstance(node, ast.Constant) and isinstance(node.value, str) and BENCH in node.value:
            found.append(repr(node.value[:80]))
    return found


def _modules(package: str) -> list[Path]:
    """The package's modules, its tests and setup.py aside."""
    return [
        path
        for path in sorted((ROOT / package).rglob("*.py"))
        if "test" not in path.relative_to(ROOT / package).parts and path.name != "setup.py"
    ]


def test_the_check_finds_every_way_of_reaching_the_benchmarks():
    source = """
import area3d_bench
from area3d_bench.soak import run_bench

def lazily():
    import area3d_bench.planner
    from area3d_bench import cli

importlib.import_module("area3d_bench.transport")
subprocess.run([sys.executable, "-m", "area3d_bench.soak_manager"])
"""
    assert len(bench_references(source)) == 6
    assert bench_references("import area3d_bringup.cli\nfrom area3d_eval import report\n") == []


@pytest.mark.parametrize("package", RUNTIME_PACKAGES)
def test_no_runtime_module_imports_or_names_the_benchmarks(package):
    modules = _modules(package)
    assert modules, f"{package}: no modules found"
    found = {
        str(path.relative_to(ROOT)): refs
        for path in modules
        if (refs := bench_references(path.read_text()))
    }
    assert found == {}, f"{package} reaches into {BENCH}: {found}"


def test_no_benchmark_module_is_left_in_a_runtime_package():
    left = [
        str(path.relative_to(ROOT))
        for package in RUNTIME_PACKAGES
        for path in _modules(package)
        if "bench" in path.stem
    ]
    assert left == []
