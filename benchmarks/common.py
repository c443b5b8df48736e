"""What the benchmarks share: where results go and which machine wrote them, timing and memory
helpers, the quiet log of the fusion runs, and the synthetic multi-date scene of the fusion benchmarks
(command-line size options, rendering the first dates once, the ground-truth Sim(3)s)."""

from __future__ import annotations

import argparse
import json
import os
import platform
import re
import sys
import time
from pathlib import Path

RESULTS = Path(__file__).resolve().parent / "results"
#: The fusion stages whose wall times make a fusion's cost.
FUSION_STAGES = ("merge", "cross_init", "refine", "export")


def timed(f, args) -> float:
    """Wall seconds of one call of ``f(*args)``, its outputs ready."""
    import jax

    t0 = time.perf_counter()
    jax.block_until_ready(f(*args))
    return time.perf_counter() - t0


def alternately(functions: dict, reps: int) -> dict:
    """Median wall seconds of each ``name: (f, args)`` in ``functions``, called in turn ``reps`` rounds
    (so that the machine's load falls on every side alike), outputs ready; compile before calling."""
    import statistics

    import jax

    times = {k: [] for k in functions}
    for _ in range(reps):
        for k, (f, args) in functions.items():
            t0 = time.perf_counter()
            jax.block_until_ready(f(*args))
            times[k].append(time.perf_counter() - t0)
    return {k: statistics.median(v) for k, v in times.items()}


def machine() -> str:
    """The CPU (or accelerator and host), core count and JAX version, for the results' headers."""
    import jax

    cpu = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    dev = jax.devices()[0]
    if dev.platform != "cpu":
        return f"{dev.device_kind} ({dev.platform}), host {cpu}, {os.cpu_count()} cores, jax {jax.__version__}"
    return f"{cpu}, {os.cpu_count()} cores, jax {jax.__version__} on {jax.default_backend()}"


def backend_suffix() -> str:
    """The result files' suffix: empty on the CPU; on an accelerator the chip and the backend, e.g.
    ``_h200_gpu``, so that an accelerator run never overwrites the CPU tables nor another chip's."""
    import jax

    backend = jax.default_backend()
    if backend == "cpu":
        return ""
    kind = jax.devices()[0].device_kind  # e.g. "NVIDIA H100 80GB HBM3", "NVIDIA H200"
    chip = re.search(r"\b([A-Z]+\d+[A-Za-z]*)\b", kind)
    name = chip.group(1) if chip else re.sub(r"[^A-Za-z0-9]+", "", kind) or "device"
    return f"_{name.lower()}_{backend}"


def device_peak_gb() -> float | None:
    """Peak memory in use on the first accelerator (its allocator's count), or None on the CPU."""
    import jax

    dev = jax.devices()[0]
    if dev.platform == "cpu":
        return None
    stats = dev.memory_stats() or {}
    return stats.get("peak_bytes_in_use", 0) / 1e9 if stats else None


def quiet(*args, **kwargs) -> None:
    """A ``log`` for the fusion runs: the benchmark prints its own lines."""


def fusion_seconds(run: Path, prefix: str = "") -> float:
    """The wall seconds of the run's fusion stages (``prefix``: an extension's, ``extend:<date>:``)."""
    t = json.loads((run / "timings.json").read_text())
    return float(sum(t.get(prefix + s, 0.0) for s in FUSION_STAGES))


def add_scene_args(
    ap: argparse.ArgumentParser, *, width: int, height: int, images_per_date: int, spp: int, work: str
) -> None:
    """``--width --height --images-per-date --spp --config --work`` with this benchmark's defaults."""
    ap.add_argument("--width", type=int, default=width)
    ap.add_argument("--height", type=int, default=height)
    ap.add_argument("--images-per-date", type=int, default=images_per_date)
    ap.add_argument("--spp", type=int, default=spp)
    ap.add_argument("--config", default="demo")
    ap.add_argument("--work", default=work)


def scene_dates(
    preset: str, args: argparse.Namespace, count: int | None = None, *, work: str | Path | None = None
) -> tuple[Path, list[str], Path, dict]:
    """Render the preset's first ``count`` dates (None: all) into WORK/data (once; WORK: ``work``, else
    ``--work``) and write their ground-truth Sim(3)s to WORK/data/transforms.json → (data dir, date
    names, transforms path, Sim(3) dicts)."""
    from cfgs_jax import synthetic

    data = Path(args.work if work is None else work) / "data"
    spec = synthetic.make_preset(
        preset, seed=0, width=args.width, height=args.height, images_per_date=args.images_per_date, spp=args.spp
    )
    count = len(spec.dates) if count is None else count
    names = [d.name for d in spec.dates][:count]
    if not (data / "ground_truth.json").is_file():
        synthetic.render_dataset(spec, data, dates=list(range(count)), progress=False)
    sims = synthetic.reference_transforms(data, names)
    transforms = data / "transforms.json"
    transforms.write_text(json.dumps(sims))
    return data, names, transforms, sims


def result_header(args: argparse.Namespace) -> dict:
    """The header every result file starts with: the command that made it (this script and its
    arguments), the date, the machine and the parsed arguments."""
    import datetime
    import shlex

    return {
        "command": "python benchmarks/" + Path(sys.argv[0]).name + " " + " ".join(shlex.quote(a) for a in sys.argv[1:]),
        "date": datetime.date.today().isoformat(),
        "machine": machine(),
        "args": vars(args),
    }


def write_result(stem: str, result: dict, markdown: str) -> None:
    """``results/STEM.json`` (the result; paths and other values JSON lacks written as text) and
    ``results/STEM.md`` (its table); the table is printed."""
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / f"{stem}.json").write_text(json.dumps(result, indent=1, default=str))
    (RESULTS / f"{stem}.md").write_text(markdown)
    print(markdown)


def random_scene(n: int, seed: int, width: int, height: int):
    """``n`` random Gaussians (float32; sizes, opacities and colours spread as a trained model's) within
    the unit cube, and a ``width``×``height`` camera looking at it from (0, −4, 1): inputs for kernel
    probes that need no trained model."""
    import jax.numpy as jnp
    import numpy as np

    import cfgs_jax as cj

    rng = np.random.default_rng(seed)
    f32 = lambda x: jnp.asarray(x, jnp.float32)
    g = cj.Gaussians(
        f32(rng.uniform(-1, 1, (n, 3))),
        f32(rng.normal(size=(n, 4))),
        f32(rng.normal(-2.3, 0.6, (n, 3))),
        f32(rng.normal(1.0, 1.5, n)),
        f32(rng.uniform(-0.1, 1.1, (n, 3))),
    )
    return g, cj.Camera.look_at([0, -4, 1], [0, 0, 0], width=width, height=height, fov_x_deg=50)


def dispatch(entry: str, doc: str, commands: dict[str, tuple[str, str]], argv: list[str] | None = None) -> None:
    """A topic's entry point: ``commands`` maps each subcommand to (the module beside this one that runs it,
    one line of help). ``python benchmarks/ENTRY.py NAME ARGS…`` imports the module and calls its
    ``main()`` with ``sys.argv`` = ["…/ENTRY.py NAME", ARGS…], so the module parses its own options (its
    usage and the command its results record read ``ENTRY.py NAME``); ``NAME --help`` shows them."""
    import importlib

    ap = argparse.ArgumentParser(
        prog=Path(entry).name, description=doc, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    sub = ap.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for name, (_, text) in commands.items():
        sub.add_parser(name, help=text, add_help=False)
    args, rest = ap.parse_known_args(sys.argv[1:] if argv is None else argv)
    module = importlib.import_module(commands[args.command][0])
    sys.argv = [f"{entry} {args.command}", *rest]
    module.main()
