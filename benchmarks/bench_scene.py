"""The synthetic multi-date scene the fusion benchmarks (bench_extend, bench_incremental) share:
command-line size options, rendering the first dates once, and the ground-truth Sim(3)s."""

from __future__ import annotations

import argparse
import json
from pathlib import Path


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


def scene_dates(preset: str, args: argparse.Namespace, count: int) -> tuple[Path, list[str], Path, dict]:
    """Render the preset's first ``count`` dates into WORK/data (once) and write their ground-truth
    Sim(3)s to WORK/data/transforms.json → (data dir, date names, transforms path, Sim(3) dicts)."""
    from cfgs_jax import synthetic

    data = Path(args.work) / "data"
    spec = synthetic.make_preset(
        preset, seed=0, width=args.width, height=args.height, images_per_date=args.images_per_date, spp=args.spp
    )
    names = [d.name for d in spec.dates][:count]
    if not (data / "ground_truth.json").is_file():
        synthetic.render_dataset(spec, data, dates=list(range(count)), progress=False)
    sims = synthetic.reference_transforms(data, names)
    transforms = data / "transforms.json"
    transforms.write_text(json.dumps(sims))
    return data, names, transforms, sims
