"""Shared test fixtures: the files under tests/data (a real 3DGS model, the LPIPS example images) and
small deterministic scenes."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest


def _cache_folder() -> Path | None:
    """The tests' cache folder: ``CFGS_JAX_CACHE``, else ``~/.cache/cfgs_jax/xla``; None for ``off``."""
    where = os.environ.get("CFGS_JAX_CACHE", str(Path.home() / ".cache" / "cfgs_jax" / "xla"))
    return None if where == "off" else Path(where)


def _persistent_compilation_cache() -> None:
    """Keep XLA's compiled executables on disk between test runs (most of a cold run is compilation).

    Set through the environment before JAX is imported, so the CLI subprocesses the tests start use
    the same cache. The folder lives outside the checkout and the venv (a fresh clone reuses it);
    ``CFGS_JAX_CACHE`` moves it, ``CFGS_JAX_CACHE=off`` turns it off. JAX keys every entry by the
    program, the compiler options and the JAX/jaxlib version, so a stale entry is never used."""
    where = _cache_folder()
    if where is None:
        return
    os.environ.setdefault("JAX_COMPILATION_CACHE_DIR", str(where))
    os.environ.setdefault("JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS", "0")
    os.environ.setdefault("JAX_PERSISTENT_CACHE_MIN_ENTRY_SIZE_BYTES", "0")
    if "PYTEST_XDIST_WORKER" not in os.environ:  # once per session, in the controlling process
        _trim(Path(os.environ["JAX_COMPILATION_CACHE_DIR"]))


def _trim(folder: Path, high: int = 2 * 1024**3, low: int = 1024**3) -> None:
    """Above ``high`` bytes, delete the least recently modified entries down to ``low``. (JAX's own
    size limit keeps access-time files that concurrent pytest workers race on, so it is not used.)"""
    if not folder.is_dir():
        return
    stats = [(p.stat(), p) for p in folder.iterdir() if p.is_file()]
    entries = sorted((st.st_mtime, st.st_size, p) for st, p in stats)
    total = sum(size for _, size, _ in entries)
    if total <= high:
        return
    for _, size, path in entries:
        if total <= low:
            break
        path.unlink(missing_ok=True)
        total -= size


def _quick_cpu_compiles() -> None:
    """Compile the tests' programs for the CPU with XLA's elemental IR emitter instead of its newer MLIR
    fusion emitters (``--xla_cpu_use_fusion_emitters=false``).

    Most of a cold test run is XLA compiling thousands of programs that then run once or a few times on
    small scenes; the fusion emitters give each fusion an MLIR pipeline of its own, and a large share of
    that compile time goes there (docs/decisions.md). The flag changes how a fusion is turned into machine code, not the operations it
    computes (no fast-math), and every test passes with and without it (``.ci/nightly`` runs the slow tier
    with XLA's defaults). Set through the environment before JAX starts its CPU backend, so the CLI
    subprocesses the tests start compile the same way. ``CFGS_JAX_TEST_COMPILE=default`` keeps XLA's
    defaults, as a user's run has them; so does a machine with an NVIDIA GPU, whose tests should compile
    as its runs do."""
    if os.environ.get("CFGS_JAX_TEST_COMPILE", "quick") != "quick" or shutil.which("nvidia-smi"):
        return
    flags = os.environ.get("XLA_FLAGS", "")
    quick = "--xla_cpu_use_fusion_emitters=false"
    if quick.split("=")[0] in flags:
        return
    # XLA aborts on a flag it does not know (older or newer jaxlib); ask a throwaway process first. The
    # xdist workers inherit the answer through the environment.
    probe = [sys.executable, "-c", "import jax; jax.devices()"]
    env = {**os.environ, "XLA_FLAGS": f"{flags} {quick}".strip(), "JAX_PLATFORMS": "cpu"}
    if subprocess.run(probe, env=env, capture_output=True, timeout=300).returncode == 0:
        os.environ["XLA_FLAGS"] = env["XLA_FLAGS"]


_persistent_compilation_cache()
_quick_cpu_compiles()

import cfgs_jax  # noqa: E402, F401  (first: loads the system libz before any test module imports pycolmap)

REPO = Path(__file__).resolve().parents[1]
FIXTURES = REPO / "tests" / "data"  # files no one here wrote; sources and licences in its README
DONUT_PLY = FIXTURES / "real_3dgs_donut_dc_only.ply"

#: What a rendered synthetic dataset depends on besides its spec: the modules that render and write it, and
#: the packages they call.
_RENDERER_SOURCES = ("synthetic/*.py", "colour.py", "sim3.py", "model.py", "io/atomic.py", "io/images.py")
_RENDERER_PACKAGES = ("mitsuba", "drjit", "pycolmap", "numpy", "scipy", "pillow")


def rendered_dataset(spec, out: Path, *, dates) -> Path:
    """``synthetic.render_dataset(spec, out, dates=dates)``, kept between test runs in the compilation cache's
    folder (``CFGS_JAX_CACHE``, under ``datasets/``): path tracing the images is most of the warm run time of
    the tests that need a dataset larger than a few views. An entry's key is the spec, the dates, the source of
    the modules that render and write a dataset and the versions of the packages they call, so a changed
    renderer renders again; a new key is rendered to a staging folder and renamed into place (two workers
    may render the same one; the first rename wins). The test gets its own copy under ``out``.
    ``CFGS_JAX_CACHE=off`` renders every time; ``tests/synthetic/test_dataset.py``, which tests the renderer, never
    reads an entry."""
    import hashlib
    import pickle
    import tempfile
    from importlib import metadata

    from cfgs_jax import synthetic

    where = _cache_folder()
    if where is None:
        return synthetic.render_dataset(spec, out, dates=dates, progress=False)
    key = hashlib.sha256(pickle.dumps((spec, sorted(dates))))
    package = REPO / "src" / "cfgs_jax"
    for source in sorted(f for pattern in _RENDERER_SOURCES for f in package.glob(pattern)):
        key.update(source.read_bytes())
    for name in _RENDERER_PACKAGES:
        key.update(f"{name} {metadata.version(name)}".encode())
    store = where / "datasets"
    store.mkdir(parents=True, exist_ok=True)
    entry = store / key.hexdigest()[:32]
    if not entry.is_dir():
        staging = Path(tempfile.mkdtemp(dir=store, prefix=".staging-"))
        synthetic.render_dataset(spec, staging, dates=dates, progress=False)
        try:
            staging.rename(entry)
        except OSError:  # another worker stored the same key first
            shutil.rmtree(staging, ignore_errors=True)
        _trim_datasets(store)
    os.utime(entry)  # recently used: the trim keeps it
    shutil.copytree(entry, out, dirs_exist_ok=True)
    return Path(out)


def _trim_datasets(store: Path, keep: int = 12) -> None:
    """Delete all but the ``keep`` most recently used datasets of ``store`` (and staging folders over a day old,
    left by a killed run)."""
    import time

    entries = sorted((p for p in store.iterdir() if p.is_dir()), key=lambda p: p.stat().st_mtime, reverse=True)
    stale = [p for p in entries if p.name.startswith(".staging-") and time.time() - p.stat().st_mtime > 86400]
    kept = [p for p in entries if not p.name.startswith(".staging-")]
    for path in stale + kept[keep:]:
        shutil.rmtree(path, ignore_errors=True)


@pytest.fixture(autouse=True, scope="module")
def _release_compiled_code():
    """After each test module: drop JAX's compiled executables. XLA:CPU keeps ~12 memory mappings per
    executable and one pytest process compiles thousands; at Linux's 65 530-mapping cap the next XLA
    compilation deadlocks (the suite hung there in CI). See cfgs_jax.compiled_code."""
    yield
    from cfgs_jax.compiled_code import release

    release()


@pytest.fixture(scope="session")
def fixtures_dir() -> Path:
    assert FIXTURES.is_dir(), f"fixtures missing: {FIXTURES} (they are part of the repository)"
    return FIXTURES


@pytest.fixture(scope="session")
def donut_path() -> Path:
    assert DONUT_PLY.is_file(), f"fixture missing: {DONUT_PLY} (it is part of the repository)"
    return DONUT_PLY


#: Refinement settings that change nothing but o (the visibility rule): every rate 0, no halving,
#: a fixed background.
FROZEN = dict(
    lr_o=0.0,
    lr_alpha=0.0,
    lr_color=0.0,
    lr_other=0.0,
    position_lr_scale=0.0,
    halve_alpha=False,
    random_background=False,
)


def small_random_gaussians(n: int, seed: int = 0):
    """Random Gaussians in the unit cube around the origin, small (scales 0.02–0.08), opacity logits around
    0.5 and colours uniform in [0, 1], float32: a few render as separate blobs in a small image."""
    from cfgs_jax import Gaussians

    rng = np.random.default_rng(seed)
    return Gaussians(
        rng.uniform(-0.5, 0.5, (n, 3)).astype(np.float32),
        rng.normal(size=(n, 4)).astype(np.float32),
        np.log(rng.uniform(0.02, 0.08, (n, 3))).astype(np.float32),
        rng.normal(0.5, 1.0, n).astype(np.float32),
        rng.uniform(size=(n, 3)).astype(np.float32),
    )


def random_gaussians(n: int, seed: int = 0):
    """Random Gaussians with generic (non-degenerate) parameters, float32.

    Colours are drawn as SH DC coefficients, as every model read from a 3DGS PLY has them, so they
    are exactly representable in the PLY layouts (see ``model.sh_dc_from_colors``)."""
    from cfgs_jax import Gaussians
    from cfgs_jax.model import colors_from_sh_dc

    rng = np.random.default_rng(seed)
    return Gaussians(
        rng.normal(size=(n, 3)).astype(np.float32),
        rng.normal(size=(n, 4)).astype(np.float32),
        rng.normal(-2.0, 0.5, size=(n, 3)).astype(np.float32),
        rng.normal(size=(n,)).astype(np.float32),
        colors_from_sh_dc(rng.uniform(-2.5, 2.5, size=(n, 3)).astype(np.float32)),
    )


def random_temporal(n: int, t: int, seed: int = 0):
    from cfgs_jax import DateInfo, TemporalGaussians

    rng = np.random.default_rng(seed + 1000)
    origin = np.sort(rng.integers(0, t, size=n)).astype(np.int32)
    return TemporalGaussians(
        random_gaussians(n, seed),
        rng.normal(size=(n, t)).astype(np.float32),
        rng.normal(size=(n, t, 3)).astype(np.float32),
        origin,
        tuple(DateInfo(f"date{i}", captured=f"2025-0{i + 1}-15", sources=(f"d{i}/point_cloud.ply",)) for i in range(t)),
    )


def bits_equal(a, b) -> bool:
    a, b = np.asarray(a), np.asarray(b)
    return a.dtype == b.dtype and a.shape == b.shape and a.tobytes() == b.tobytes()


import warnings  # noqa: E402

from hypothesis import HealthCheck, settings  # noqa: E402

# Hypothesis profiles for the stress suite (tests/stress): "ci" is the default (bounded and
# derandomised: same examples every run); "thorough" via --hypothesis-profile=thorough.
_SLOW_OK = [HealthCheck.too_slow, HealthCheck.data_too_large]
settings.register_profile(
    "ci", max_examples=12, deadline=None, derandomize=True, suppress_health_check=_SLOW_OK, print_blob=True
)
settings.register_profile("thorough", max_examples=400, deadline=None, suppress_health_check=_SLOW_OK, print_blob=True)
settings.load_profile("ci")

warnings.filterwarnings("ignore", message=".*Matplotlib.*")


def pytest_collection_modifyitems(config, items):
    """Everything under tests/stress/ carries the ``stress`` marker (select with -m stress)."""
    import pytest

    for item in items:
        if "stress" in Path(str(item.fspath)).parts:
            item.add_marker(pytest.mark.stress)


# ---------------------------------------------- a tiny fused run through the CLI, shared by the app tests


def _built_once(tmp_path_factory, name: str, build) -> Path:
    """A folder ``build(folder)`` fills once per test session, shared by every pytest-xdist worker: the
    first worker to ask builds it under an exclusive file lock while the others wait, then read it (the
    app tests of several files share one fused run, which took each worker its own fusion before).
    The tests only read such a folder; one that changes a run copies it first."""
    import fcntl
    import shutil

    base = tmp_path_factory.getbasetemp()
    root = base.parent if os.environ.get("PYTEST_XDIST_WORKER") else base  # the session's folder under xdist
    folder = root / f"shared-{name}"
    with open(root / f"shared-{name}.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        if not (folder / ".built").is_file():
            shutil.rmtree(folder, ignore_errors=True)
            folder.mkdir()
            build(folder)
            (folder / ".built").write_text("")
    return folder


@pytest.fixture(scope="session")
def tiny_two_dates(tmp_path_factory):
    """Two corals dates at 64×48 (6 views each) and their ground-truth date → reference Sim(3)s."""
    import json

    from cfgs_jax import synthetic

    def build(root: Path) -> None:
        spec = synthetic.make_preset("corals", seed=5, width=64, height=48, images_per_date=6, spp=4)
        rendered_dataset(spec, root, dates=[0, 1, 2])
        (root / "transforms.json").write_text(json.dumps(synthetic.reference_transforms(root, ["d0", "d1", "d2"])))
        (root / "tiny.toml").write_text(
            "[train]\nsteps = 60\ndensify_from = 20\ndensify_until = 50\ndensify_interval = 20\n"
            "sh_degree = 2\nsh_interval = 20\n"  # view-dependent colour through every stage
            "[cross_init]\nsteps = 15\nrate_reference_steps = 0\n[refine]\nsteps = 20\nvisibility_interval = 10\n"
        )  # the rates as given: 15 steps at 200× would saturate every o^q (the README snippet's FD check needs slopes)

    return _built_once(tmp_path_factory, "tiny", build)


@pytest.fixture(scope="session")
def fused_run(tiny_two_dates, tmp_path_factory):
    """`fuse` of d0 and d1 through the CLI; returns (run directory, its argument list)."""
    from cfgs_jax.app.pipeline import main

    root = tiny_two_dates
    args = lambda out: [
        "fuse",
        "--dates",
        str(root / "d0"),
        str(root / "d1"),
        "--out",
        str(out),
        "--config",
        str(root / "tiny.toml"),
        "--transforms",
        str(root / "transforms.json"),
        "--no-progress",
    ]

    def build(folder: Path) -> None:
        assert main(args(folder / "a")) == 0

    out = _built_once(tmp_path_factory, "fused", build) / "a"
    return out, args(out)


@pytest.fixture(scope="session")
def extended_run(tiny_two_dates, fused_run, tmp_path_factory):
    """A copy of `fused_run` extended by d2 through the CLI (d2 trained in the run), the extension
    refining 7 steps with the visibility rule at the added date only; returns its directory."""
    import json
    import shutil

    from cfgs_jax.app.pipeline import main

    run = tmp_path_factory.mktemp("extended") / "run"
    shutil.copytree(fused_run[0], run)
    state = json.loads((run / "run.json").read_text())  # the run's config: extension refines 7 steps, not 20
    state["config"]["refine"]["extend_steps"] = 7
    state["config"]["refine"]["extend_visibility"] = "added"  # the visibility rule at the added date only
    (run / "run.json").write_text(json.dumps(state))
    common = ["--transforms", str(tiny_two_dates / "transforms.json"), "--no-progress"]
    assert main(["extend", "--run", str(run), "--date", str(tiny_two_dates / "d2"), *common]) == 0
    return run
