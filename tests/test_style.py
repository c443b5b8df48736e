"""The code is formatted and linted with ruff (configuration in pyproject.toml), so CI fails on drift;
every JAX matrix product or convolution in the library states its precision; and no import
cycle joins two rooms of the package."""

from __future__ import annotations

import ast
import subprocess
import sys

from conftest import REPO


def _ruff(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "ruff", *args], cwd=REPO, capture_output=True, text=True)


def test_code_is_formatted():
    r = _ruff("format", "--check", ".")
    assert r.returncode == 0, "run `ruff format .`:\n" + r.stdout[-3000:] + r.stderr[-2000:]


def test_code_passes_the_linter():
    r = _ruff("check", "--output-format", "concise", ".")
    assert r.returncode == 0, "run `ruff check --fix .` and fix the rest:\n" + r.stdout[-3000:] + r.stderr[-2000:]


_PRODUCTS = {"matmul", "einsum", "dot", "tensordot", "inner", "vdot", "dot_general", "conv_general_dilated"}


def test_every_jax_product_states_its_precision():
    """A GPU runs float32 products at TF32 unless asked otherwise, which the kernel's float64
    comparisons do not survive: every ``jnp``/``lax`` product call names ``precision``, and the kernel's
    modules use no ``@``, which cannot name it. The float64 reference kernel is exempt (no GPU rounds
    float64 products)."""
    src = REPO / "src" / "cfgs_jax"
    missing = []
    for path in sorted(p for p in src.rglob("*.py") if p != src / "splat" / "reference.py"):
        tree = ast.parse(path.read_text(), filename=str(path))
        for node in ast.walk(tree):
            if isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute) and node.func.attr in _PRODUCTS:
                owner = ast.unparse(node.func.value)
                if owner in {"jnp", "jax.numpy", "lax", "jax.lax"} and not any(
                    k.arg == "precision" for k in node.keywords
                ):
                    missing.append(f"{path.relative_to(REPO)}:{node.lineno} {owner}.{node.func.attr}")
            if path.parent.name == "splat" and isinstance(node, ast.BinOp) and isinstance(node.op, ast.MatMult):
                missing.append(f"{path.relative_to(REPO)}:{node.lineno} @")
    assert not missing, "name precision=jax.lax.Precision.HIGHEST (or use jnp.matmul with it):\n" + "\n".join(missing)


def _house():
    import importlib.util

    spec = importlib.util.spec_from_file_location("house", REPO / "tools" / "house.py")
    house = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(house)
    return house


def test_no_two_rooms_of_the_package_import_each_other_round_a_circle():
    """``tools/house.py``'s rooms (subpackages and top-level modules) form no import cycle, counting
    imports inside functions: a circle makes a room impossible to read, test or move on its own."""
    assert _house().room_cycles(REPO) == []


def test_nothing_below_the_application_layer_imports_it():
    """The library (every module but ``cfgs_jax.app`` and the entry point ``cfgs_jax.pipeline``)
    imports nothing of the application layer: the arrows point down, so the library runs without it."""
    assert _house().upward_arrows(REPO) == []


def test_no_function_outside_the_kernel_runs_over_sixty_lines():
    """Outside ``splat/`` (whose kernels keep a pass in one piece) every function fits on a screen:
    sixty lines, its docstring included."""
    assert _house().long_functions(REPO) == []


#: Test files of the whole repository rather than of one module: the style, the benchmarks' scripts,
#: the installed wheel and the shipped configurations.
REPOSITORY_WIDE = {"test_style.py", "test_benchmarks.py", "test_cli_install.py", "test_shipped_configs.py"}


def test_test_files_mirror_the_modules_they_test():
    """``tests/<package>/test_<module>[_<what>].py`` tests ``src/cfgs_jax/<package>/<module>.py``; the
    property-based suite keeps ``tests/stress/``; the repository-wide files sit at the top beside the
    files of top-level modules."""
    src = REPO / "src" / "cfgs_jax"
    tests = REPO / "tests"
    stray = []
    for path in sorted(tests.rglob("test_*.py")):
        rel = path.relative_to(tests)
        if rel.parts[0] == "stress" or (len(rel.parts) == 1 and rel.name in REPOSITORY_WIDE):
            continue
        modules = {p.stem for p in (src / rel.parent).glob("*.py") if p.stem != "__init__"}
        stem = path.stem.removeprefix("test_")
        if not any(stem == m or stem.startswith(f"{m}_") for m in modules):
            stray.append(str(rel))
    assert not stray, f"no module of src/cfgs_jax matches: {stray}"
    assert all((tests / name).is_file() for name in REPOSITORY_WIDE)
