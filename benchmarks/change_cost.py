"""Cost of the change detector's residual sums, side by side in one run: for one observing date q of a
finished fusion run and the first V of its views, every other date's Gaussians are tested at q (the
``changes`` detector's inner loop, ``changes.evidence.observing_date_sums``) three ways:

- ``gradient``: one pair at a time, the weighted sums Σ w·map taken as the gradient of Σ map·C with
  respect to a per-Gaussian colour multiplier (a forward and a backward walk of the kernel);
- ``forward``: one pair at a time, the sums from one forward walk (``splat.summed_weight_maps``);
- ``forward, D per pass``: D dates at once, sharing each view's projection, sort and walks
  (``changes.dates_per_pass``).

Every method's sums are checked against the first's (largest relative difference reported).

    python benchmarks/bench_change.py cost --run RUN [--date 1] [--views 6] [--per-pass 1 4]

Writes benchmarks/results/NAME.json and NAME.md (``--name``, default change_cost).
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime
import functools
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import RESULTS, machine


def _gradient_sums(model, dates, q, cameras, images, rc):
    """The residual sums of each date p in ``dates`` at q, the weighted sums by a backward pass (the
    method the forward walk replaced), one pair at a time."""
    import jax
    import jax.numpy as jnp
    import numpy as np

    from cfgs_jax import splat
    from cfgs_jax.changes.evidence import premultiplied
    from cfgs_jax.model import light_multipliers, opacity_multipliers

    @functools.partial(jax.jit, static_argnames=("config",))
    def one_view(g, cam, present, absent, light, image, config):
        res = splat.render_dates(
            g, cam, jnp.stack([present, absent]), jnp.broadcast_to(light, (2,) + light.shape), config=config
        )
        plus, minus = res.image[0], res.image[1]
        dot = lambda a, b: jnp.sum(a * b, axis=-1)
        maps = jnp.stack(  # six maps packed as two RGB masks, one per layer
            [
                jnp.stack([jnp.ones(image.shape[:2], image.dtype), dot(plus, image), dot(plus, plus)], -1),
                jnp.stack([dot(minus, image), dot(minus, minus), dot(image, image)], -1),
            ]
        )
        ones = dataclasses.replace(g, colors=jnp.ones_like(g.colors))
        n = len(g)

        def weighted(mult):
            r = splat.render_dates(ones, cam, jnp.broadcast_to(present, (2, n)), mult, config=config, statistics=False)
            return jnp.sum(r.image * jax.lax.stop_gradient(maps))

        w = jax.grad(weighted)(jnp.ones((2, n, 3), image.dtype))  # [2, N, 3]
        return jnp.concatenate([w[0], w[1]], axis=-1), res.max_weight[0]

    o = np.asarray(opacity_multipliers(model), np.float32)
    origin = np.asarray(model.origin)
    light = jnp.asarray(light_multipliers(model)[:, q], jnp.float32)
    out = {}
    for p in dates:
        own = origin == p
        present = jnp.asarray(np.where(own, o[:, p], o[:, q]))
        absent = jnp.asarray(np.where(own, 0.0, o[:, q]).astype(np.float32))
        total = np.zeros((int(own.sum()), 6))
        for cam, image in zip(cameras, images):
            cap = splat.required_capacity(model.gaussians, cam, jnp.stack([present, absent]), config=rc)
            sums, _ = one_view(
                model.gaussians,
                cam,
                present,
                absent,
                light,
                jnp.asarray(premultiplied(image)),
                dataclasses.replace(rc, capacity=cap),
            )
            total += np.asarray(sums)[own]
        out[p] = total
    return out


def main(argv: list[str]):
    """``bench_change.py cost``: parse ``argv``, measure and write the results."""
    ap = argparse.ArgumentParser(
        prog="bench_change.py cost", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--run", required=True, help="a finished fusion run (read only)")
    ap.add_argument("--date", type=int, default=1, help="the observing date q (index)")
    ap.add_argument("--views", type=int, default=6, help="the first V of q's views")
    ap.add_argument("--per-pass", type=int, nargs="+", default=[1, 4], help="dates per pass of the forward walk")
    ap.add_argument("--name", default="change_cost")
    args = ap.parse_args(argv)

    import numpy as np

    from cfgs_jax.app.render_run import open_run
    from cfgs_jax.changes.evidence import observing_date_sums
    from cfgs_jax.io.atomic import write_json, write_text
    from cfgs_jax.io.run_dir import date_views

    run_dir = Path(args.run)
    run = open_run(run_dir)
    rc = run.config.render
    model, q = run.model, args.date
    views = date_views(run.scenes[q], run.sims[q], "all")
    cameras, images = list(views.cameras)[: args.views], list(views.images)[: args.views]
    dates = [p for p in range(model.num_dates) if p != q]
    methods = [("gradient, one pair at a time", None)] + [
        (f"forward walk, {d} date{'s' if d > 1 else ''} per pass", d) for d in args.per_pass
    ]

    def run_method(per_pass):
        if per_pass is None:
            return _gradient_sums(model, dates, q, cameras, images, rc)
        got = observing_date_sums(model, dates, q, cameras, images, render_config=rc, dates_per_pass=per_pass)
        return {p: got[p][0] for p in dates}

    rows, first = [], None
    for label, per_pass in methods:
        # compile every shape first (capacities differ per view; the gradient's shapes are the same for
        # every pair, so one pair warms it), then time the whole set
        if per_pass is None:
            _gradient_sums(model, dates[:1], q, cameras, images, rc)
        else:
            run_method(per_pass)
        start = time.perf_counter()
        sums = run_method(per_pass)
        seconds = time.perf_counter() - start
        first = first or sums
        scale = max(float(np.abs(first[p]).max()) for p in dates)
        diff = max(float(np.abs(sums[p] - first[p]).max()) for p in dates) / scale
        rows.append(
            {
                "method": label,
                "seconds": seconds,
                "per_pair_view": seconds / (len(dates) * len(cameras)),
                "max_rel_diff": diff,
            }
        )
        print(rows[-1], flush=True)

    command = f"python benchmarks/bench_change.py cost --run {args.run} --date {q} --views {args.views} --per-pass {' '.join(map(str, args.per_pass))}"
    result = {
        "command": command,
        "machine": machine(),
        "date": datetime.date.today().isoformat(),
        "gaussians": len(model.gaussians),
        "dates": model.num_dates,
        "image": [int(cameras[0].width), int(cameras[0].height)],
        "views": len(cameras),
        "pairs": len(dates),
        "rows": rows,
    }
    base = rows[0]["seconds"]
    lines = [
        "# The change detector's residual sums: cost per method (bench_change.py cost)",
        "",
        f"Command: `{command}`. Machine: {result['machine']}. Date: {result['date']}. Model: "
        f"{result['gaussians']:,} Gaussians, {result['dates']} dates; observing date {q}, its first "
        f"{len(cameras)} views at {cameras[0].width}x{cameras[0].height}, {len(dates)} ordered pairs.",
        "",
        "| method | wall (s) | per pair and view (s) | against the gradient | largest relative difference |",
        "|---|---:|---:|---:|---:|",
    ]
    for r in rows:
        lines.append(
            f"| {r['method']} | {r['seconds']:.1f} | {r['per_pair_view']:.2f} | {r['seconds'] / base:.2f}× | {r['max_rel_diff']:.1e} |"
        )
    lines.append("")
    lines.append(
        "The relative difference is the largest absolute difference of any of the six sums over the largest sum."
    )
    write_json(RESULTS / f"{args.name}.json", result)
    write_text(RESULTS / f"{args.name}.md", "\n".join(lines) + "\n")
    print("\n".join(lines))
