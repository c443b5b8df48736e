"""The XLA tile compositor (or the binning) of the working tree against the one of a git revision, side by
side in one process.

Only ``src/cfgs_jax/splat/composite.py`` (``--module composite``, the default) or
``src/cfgs_jax/splat/binning.py`` (``--module binning``) differs between the two sides: the base revision's
file is loaded as a module of its own and its ``composite`` (or ``bin_gaussians``) put in place of the working
tree's while that side's programs are traced, so everything else in the frame is the same code. For each case
(``kernel_splat``'s scenes, named as there) and each side, three whole frames are compiled ahead of time:

- ``forward``: ``render`` (images and statistics);
- ``fwd+bwd``: an L1 image loss and its gradient with respect to every raw parameter (a training or
  refinement step's frame);
- ``fwd+bwd, multipliers``: the gradient of the opacity and colour multipliers alone (cross-timestep
  initialisation's frame).

They are timed alternately (median of ``--reps`` rounds); the table gives each side's time, the ratio
working tree / base, and the largest difference between the two sides' images and gradients (relative
to each array's largest magnitude), so that a faster compositor is seen to compute the same thing.

    python benchmarks/bench_kernel.py revision [--base REV] [--module composite|binning]
        [--cases 20k@320x240 ...] [--reps 7] [--tag T]

Writes ``results/composite_revision{TAG}{chip}.{json,md}`` (``binning_revision…`` with ``--module binning``).
"""

from __future__ import annotations

import argparse
import dataclasses
import importlib.util
import subprocess
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import alternately, backend_suffix, result_header, write_result
from kernel_splat import case, scene

REPO = Path(__file__).resolve().parents[1]
#: --module: (the file that differs, the function of it that ``cfgs_jax.splat.render`` calls, what it is,
#: the result files' stem)
MODULES = {
    "composite": ("src/cfgs_jax/splat/composite.py", "composite", "XLA compositor", "composite_revision"),
    "binning": ("src/cfgs_jax/splat/binning.py", "bin_gaussians", "binning", "binning_revision"),
}
KINDS = ("forward", "fwd+bwd", "fwd+bwd, multipliers")


def load_base(rev: str, module: str = "composite"):
    """The module ``MODULES[module]`` as it is at git revision ``rev`` (a module of its own, not registered
    as part of the package)."""
    text = subprocess.run(
        ["git", "show", f"{rev}:{MODULES[module][0]}"], cwd=REPO, capture_output=True, text=True, check=True
    )
    folder = Path(tempfile.mkdtemp())
    path = folder / "composite_base.py"
    path.write_text(text.stdout)
    spec = importlib.util.spec_from_file_location("composite_base", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def compiled_frames(g, cam, config, target, compositor, attribute: str = "composite"):
    """The three frames of ``KINDS`` compiled with ``compositor`` in place of the package's ``attribute``
    of ``cfgs_jax.splat.render`` (its compositor, or its binning): {kind: (compiled function, args)}."""
    import jax
    import jax.numpy as jnp

    from cfgs_jax import splat

    # the module (the package also exports a function named ``render``)
    render = importlib.import_module("cfgs_jax.splat.render")
    n = len(g)
    om, cm = jnp.ones((1, n), jnp.float32), jnp.ones((1, n, 3), jnp.float32)

    def loss(g, om, cm):
        return jnp.mean(jnp.abs(splat.render_dates(g, cam, om, cm, config=config).image[0] - target))

    frames = {
        "forward": (jax.jit(lambda g, om, cm: splat.render_dates(g, cam, om, cm, config=config)), (g, om, cm)),
        "fwd+bwd": (jax.jit(jax.value_and_grad(loss, argnums=(0, 1, 2))), (g, om, cm)),
        "fwd+bwd, multipliers": (jax.jit(jax.value_and_grad(loss, argnums=(1, 2))), (g, om, cm)),
    }
    saved = getattr(render, attribute)
    setattr(render, attribute, compositor)
    try:
        jax.clear_caches()  # the package's jitted render traces again, with this compositor
        return {k: (f.lower(*args).compile(), args) for k, (f, args) in frames.items()}
    finally:
        setattr(render, attribute, saved)


def largest_difference(a, b) -> float:
    """max |a − b| / max |a| over the arrays of two outputs."""
    import jax
    import numpy as np

    worst = 0.0
    for x, y in zip(jax.tree_util.tree_leaves(a), jax.tree_util.tree_leaves(b)):
        x, y = np.asarray(x, np.float64), np.asarray(y, np.float64)
        if x.size and np.abs(x).max() > 0:
            worst = max(worst, float(np.abs(x - y).max() / np.abs(x).max()))
    return worst


def run_case(name: str, base, reps: int, module: str = "composite") -> dict:
    import jax
    import jax.numpy as jnp
    import numpy as np

    from cfgs_jax import splat

    working = importlib.import_module(f"cfgs_jax.splat.{module}")
    attribute = MODULES[module][1]

    kind, n, w, h = case(name)
    g, cam = scene(kind, n, w, h)
    ones = jnp.ones((1, len(g)), jnp.float32)
    config = splat.RenderConfig(backend="xla")
    config = dataclasses.replace(config, capacity=splat.required_capacity(g, cam, ones, config=config))
    target = jnp.asarray(np.random.default_rng(2).uniform(size=(h, w, 3)), jnp.float32)
    sides = {
        "base": compiled_frames(g, cam, config, target, getattr(base, attribute), attribute),
        "working tree": compiled_frames(g, cam, config, target, getattr(working, attribute), attribute),
    }
    outputs = {s: {k: jax.block_until_ready(f(*a)) for k, (f, a) in frames.items()} for s, frames in sides.items()}
    seconds = alternately({(s, k): sides[s][k] for k in KINDS for s in sides}, reps)
    rows = {}
    for k in KINDS:
        b, t = seconds["base", k], seconds["working tree", k]
        rows[k] = {
            "base_s": b,
            "working_s": t,
            "ratio": t / b,
            "largest_difference": largest_difference(outputs["base"][k], outputs["working tree"][k]),
        }
    return {"case": name, "gaussians": len(g), "rows": rows}


def markdown(result: dict) -> str:
    lines = [
        f"# The {MODULES[result['args']['module']][2]}: working tree against a base revision",
        "",
        f"Machine: {result['machine']}. Date: {result['date']}. Command: `{result['command']}`. Base revision "
        f"{result['base']}, working tree at {result['head']}{' with changes' if result['dirty'] else ''}. Whole frames "
        f"compiled ahead of time, timed alternately, medians of {result['args']['reps']} rounds; only "
        f"`{MODULES[result['args']['module']][0]}` differs between the sides. Difference: the largest |base − working tree| over the outputs (image "
        "and statistics, or loss and gradients), relative to each array's largest magnitude.",
        "",
        "| case | frame | base | working tree | working / base | difference |",
        "|---|---|---:|---:|---:|---:|",
    ]
    for c in result["cases"]:
        for k, r in c["rows"].items():
            lines.append(
                f"| {c['case']} | {k} | {1e3 * r['base_s']:.1f} ms | {1e3 * r['working_s']:.1f} ms | "
                f"{r['ratio']:.2f} | {r['largest_difference']:.1e} |"
            )
    return "\n".join(lines) + "\n"


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--base", default="HEAD", help="git revision whose compositor is the baseline (default HEAD)")
    ap.add_argument("--module", choices=sorted(MODULES), default="composite", help="the file that differs")
    ap.add_argument("--cases", nargs="+", default=["20k@320x240", "donut@640x480", "100k@640x480"])
    ap.add_argument("--reps", type=int, default=7)
    ap.add_argument("--tag", default="")
    args = ap.parse_args()

    def git(*a):
        return subprocess.run(["git", *a], cwd=REPO, capture_output=True, text=True, check=True).stdout.strip()

    base = load_base(args.base, args.module)
    result = result_header(args) | {
        "base": git("rev-parse", "--short", args.base),
        "head": git("rev-parse", "--short", "HEAD"),
        "dirty": bool(git("status", "--porcelain", "--", MODULES[args.module][0])),
        "cases": [],
    }
    for name in args.cases:
        result["cases"].append(run_case(name, base, args.reps, args.module))
        print(name, {k: round(r["ratio"], 3) for k, r in result["cases"][-1]["rows"].items()}, flush=True)
    write_result(f"{MODULES[args.module][3]}{args.tag}{backend_suffix()}", result, markdown(result))
