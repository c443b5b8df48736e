"""Registration against ground truth: every date of each synthetic preset registered by SfM as ``fuse``
registers it (in time order, into the joint SfM of the dates before it), its Sim(3) compared with
the preset's exact one.

Per date: images registered (the date's / the earlier dates'), rotation error (degrees), scale error
(%), and translation error as the largest distance between where the found and the true Sim(3) put
the date's camera centres, in % of the scene's extent (the largest distance of the reference date's
cameras from their mean, in the reference frame); the targets are ≤ 0.5°, ≤ 1 % and ≤ 1 %.

    python benchmarks/bench_register.py [--presets vase corals flood quake glossy] [--width 160 --height 120]
        [--images-per-date 24] [--spp 16] [--work runs/bench_register] [--name register]
        [--register-images N] [--truth-anchors] [--joint-sfm-poses] [--fuse corals --dates 2 --config demo]

``--truth-anchors`` registers each date with the earlier dates at their exact Sim(3)s (an earlier date's
error then does not carry into the later ones); ``--joint-sfm-poses`` turns ``register.persistent_structure``
off, so the two together isolate what posing on the registered dates' shared points does.

``--fuse PRESET`` also fuses that preset's first ``--dates`` dates twice from the same per-date models,
with the exact Sim(3)s and with SfM registration, and reports the fused model's test PSNR / SSIM /
LPIPS of both (the target: SfM within 0.1 dB of the exact transforms).

Writes benchmarks/results/NAME.json and NAME.md.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import add_scene_args, quiet, result_header, scene_dates, write_result


def register_preset(preset: str, args) -> list[dict]:
    """Each date after the first registered into the SfM of the dates before it, against the truth."""
    from cfgs_jax import fusion
    from cfgs_jax.evaluation import registration
    from cfgs_jax.io import read_colmap
    from cfgs_jax.sim3 import Sim3

    data, names, _, truth = scene_dates(preset, args, work=Path(args.work) / preset)
    scenes = [read_colmap(data / n) for n in names]
    true = [Sim3.from_dict(truth[n]) for n in names]
    centres = [np.stack([np.asarray(c.center, np.float64) for c in sc.cameras]) for sc in scenes]
    extent = fusion.register.centre_extent(centres[0])
    config = fusion.RegisterConfig(
        **({"images_per_date": args.register_images} if args.register_images else {}),
        persistent_structure=not args.joint_sfm_poses,
    )
    picked = config.images_per_date  # the images of each date that go into the SfM
    found, rows = [Sim3.identity()], []
    for k in range(1, len(names)):
        row = {"preset": preset, "date": names[k], "with": names[:k]}
        try:
            r = fusion.register_date(list(zip(scenes[:k], found)), scenes[k], config=config)
        except Exception as exc:  # a failed registration is a result: the row says why
            rows.append(row | {"error": str(exc).splitlines()[0][:160]})
            found.append(true[k])  # the later dates register against the truth instead
            continue
        found.append(true[k] if args.truth_anchors else r.transform)
        rows.append(
            row
            | {
                "registered": [r.registered_date, r.registered_reference],
                "images": [min(len(scenes[k]), picked), sum(min(len(s), picked) for s in scenes[:k])],
            }
            | registration.registration_error(r.transform, true[k], centres[k], extent)
        )
    return rows


def fuse_both(preset: str, args) -> dict:
    """The preset's first dates fused with the exact Sim(3)s, then again from the same per-date models
    with SfM registration: each run's mean test metrics over the dates, and the SfM run's registration."""
    from cfgs_jax.config import find_preset, load_config
    from cfgs_jax.fusion import run_fusion

    work = Path(args.work) / preset
    data, names, transforms, _ = scene_dates(preset, args, args.dates, work=work)
    tables = load_config(find_preset(args.config))
    known, sfm = work / "fused_known", work / "fused_sfm"
    run_fusion(
        [data / n for n in names],
        known,
        tables,
        transforms=transforms,
        resume=known.exists(),
        progress=False,
        log=quiet,
    )
    models = [known / "dates" / n / "point_cloud.ply" for n in names]
    run_fusion([data / n for n in names], sfm, tables, models=models, resume=sfm.exists(), progress=False, log=quiet)
    mean = lambda run: json.loads((run / "metrics.json").read_text())["mean"]
    return {"preset": preset, "dates": names, "known": mean(known), "sfm": mean(sfm)}


def table(result: dict) -> str:
    a = result["args"]
    lines = [
        f"# Registration against ground truth ({result['date']})",
        "",
        f"`{result['command']}`",
        "",
        f"Machine: {result['machine']}. Synthetic presets at {a['width']}×{a['height']}, {a['images_per_date']} "
        f"images per date ({a['spp']} spp); each date registered by joint SfM with the dates before it "
        f"(`fusion.register_date`, {a.get('register_images') or 'the default'} images per date in the SfM). "
        + (
            "The earlier dates enter each registration at their exact Sim(3)s (`--truth-anchors`). "
            if a.get("truth_anchors")
            else ""
        )
        + (
            "`register.persistent_structure = false`: the new date's poses are the joint SfM's. "
            if a.get("joint_sfm_poses")
            else ""
        )
        + "Targets: rotation ≤ 0.5°, scale ≤ 1 %, "
        "translation ≤ 1 % of the scene's extent.",
        "",
        "| preset | date | with | images registered (date / earlier) | rotation (°) | scale (%) | translation (% extent) | within targets |",
        "|---|---|---|---|---:|---:|---:|---|",
    ]
    for row in result["rows"]:
        with_ = ", ".join(row["with"])
        if "error" in row:
            lines.append(f"| {row['preset']} | {row['date']} | {with_} | failed: {row['error']} | | | | no |")
            continue
        ok = row["within_targets"]
        reg, imgs = row["registered"], row["images"]
        lines.append(
            f"| {row['preset']} | {row['date']} | {with_} | {reg[0]}/{imgs[0]} / "
            f"{reg[1]}/{imgs[1]} | {row['rotation_deg']:.3f} | {row['scale_pct']:.3f} | "
            f"{row['translation_pct']:.3f} | {'yes' if ok else 'no'} |"
        )
    if "fused" in result:
        f = result["fused"]
        lines += [
            "",
            f"Fused {f['preset']} ({', '.join(f['dates'])}; configuration `{a['config']}`), test views of every date, "
            "mean over the dates, the same per-date models:",
            "",
            "| transforms | PSNR | SSIM | LPIPS |",
            "|---|---:|---:|---:|",
            *(
                f"| {label} | {f[key]['psnr']:.3f} | {f[key]['ssim']:.4f} | {f[key]['lpips']:.4f} |"
                for key, label in (("known", "exact Sim(3)s"), ("sfm", "SfM registration"))
            ),
            f"| SfM − exact | {f['sfm']['psnr'] - f['known']['psnr']:+.3f} | {f['sfm']['ssim'] - f['known']['ssim']:+.4f} "
            f"| {f['sfm']['lpips'] - f['known']['lpips']:+.4f} |",
        ]
    return "\n".join(lines) + "\n"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--presets", nargs="+", default=["vase", "corals", "flood", "quake", "glossy"])
    ap.add_argument("--name", default="register")
    ap.add_argument("--fuse", metavar="PRESET", help="also fuse this preset with exact and with SfM transforms")
    ap.add_argument("--dates", type=int, default=2, help="dates fused with --fuse")
    ap.add_argument("--register-images", type=int, help="[register] images_per_date (default: its default)")
    ap.add_argument(
        "--truth-anchors", action="store_true", help="register each date with the earlier dates at their exact Sim(3)s"
    )
    ap.add_argument(
        "--joint-sfm-poses", action="store_true", help="register.persistent_structure = false (the joint SfM's poses)"
    )
    add_scene_args(ap, width=160, height=120, images_per_date=24, spp=16, work="runs/bench_register")
    args = ap.parse_args()
    result = result_header(args) | {"rows": []}
    for preset in args.presets:
        result["rows"] += register_preset(preset, args)
        print(table(result), flush=True)
    if args.fuse:
        result["fused"] = fuse_both(args.fuse, args)
    write_result(args.name, result, table(result))


if __name__ == "__main__":
    main()
