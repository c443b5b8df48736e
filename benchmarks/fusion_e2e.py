"""A whole fusion end to end on data made by the kernel itself: per-date training, merge, cross-timestep
initialisation and refinement, with every stage's wall time and each date's test PSNR / SSIM / LPIPS of
the fused model against the date's own model.

Needs neither Mitsuba nor pycolmap (a GPU machine may lack both): the two dates' ground truth is a town
of boxes on a ground made of flat, nearly opaque Gaussians (closed surfaces, a smooth colour pattern) seen on
an orbit, rendered by ``splat.render`` into RGBA images (transparent where no surface is); date 1 has lost one
box (disappeared) and gained another (appeared). Every 7th view is a test view.
Each date is an ``io.Scene`` over the written PNGs, its "SfM points" the true centres (a subsample,
jittered). Exact Sim(3)s (identity): registration is measured elsewhere.

    python benchmarks/bench_fusion.py e2e [--size 160x120] [--gaussians 20000] [--views 28]
        [--train-steps 1500] [--cross-steps 500] [--refine-steps 1000] [--set TABLE.KEY=VALUE ...]
        [--work DIR] [--tag T]

``--set`` changes a value of the ``[train]``, ``[cross_init]`` or ``[refine]`` table as the pipeline's
``--set`` does (e.g. the refinement's rates: ``--set refine.lr_alpha=0.05``); the step counts are the
flags above. Without it every stage runs at the package defaults (the paper's rates).

Writes ``results/fusion_e2e{T}{chip}.{json,md}`` (``_<chip>_gpu`` on an accelerator).
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import backend_suffix, result_header, write_result

#: The boxes of the scene, (centre, size) with y pointing down: A and B stay, C is gone at date 1 and D
#: appears there. They stand on a 4 × 4 ground at y = 1.
_BOXES = {
    "A": ((-0.9, 0.4, 0.0), (0.8, 1.2, 0.8)),
    "B": ((0.7, 0.7, 0.5), (1.0, 0.6, 0.7)),
    "C": ((0.6, 0.6, -0.7), (0.6, 0.8, 0.6)),
    "D": ((-0.2, 0.75, -0.9), (0.5, 0.5, 0.5)),
}
_GROUND = ((0.0, 1.0, 0.0), (4.0, 0.0, 4.0))


def _surface(centre, size, n: int, rng, seed: int, faces=("x-", "x+", "y-", "z-", "z+")):
    """``n`` flat, nearly opaque Gaussians tiling the given faces of an axis-aligned box (``y-`` is the
    top; a size-0 axis is a plane), each face's share by its area; each Gaussian's extent is the mean
    spacing along the face and a tenth of it across, so the faces are closed surfaces. Colours are a
    smooth pattern of the position (a few cycles per unit), distinct per ``seed``."""
    import cfgs_jax as cj

    centre, size = np.asarray(centre, np.float64), np.asarray(size, np.float64)
    area = {f: np.prod([size[k] for k in range(3) if k != "xyz".index(f[0])]) for f in faces}
    total = sum(area.values())
    means, scales = [], []
    for f, a in area.items():
        k = "xyz".index(f[0])
        m = max(1, int(round(n * a / total)))
        p = centre + (rng.uniform(-0.5, 0.5, (m, 3)) * size)
        p[:, k] = centre[k] + (0.5 if f[1] == "+" else -0.5) * size[k]
        spacing = np.sqrt(a / m)
        s = np.full((m, 3), 1.2 * spacing)
        s[:, k] = 0.1 * spacing
        means.append(p)
        scales.append(s)
    means, scales = np.concatenate(means), np.concatenate(scales)
    pattern = np.random.default_rng(seed)
    frequency, offset = pattern.normal(0.0, 4.0, (3, 3)), pattern.uniform(0, 2 * np.pi, 3)  # rad per unit
    colors = 0.5 + 0.35 * np.sin(means @ frequency + offset)
    m = len(means)
    return cj.Gaussians(
        means.astype(np.float32),
        np.tile(np.float32([1, 0, 0, 0]), (m, 1)),
        np.log(scales).astype(np.float32),
        np.full(m, 4.0, np.float32),
        np.clip(colors, 0.05, 0.95).astype(np.float32),
    )


def _dates(n: int, seed: int = 0):
    """Two dates of a small town of boxes on a ground, made of ``n`` surface Gaussians at date 0 (half of
    them on the ground): date 1 has lost box C and gained box D; what stays is the same Gaussians."""
    import cfgs_jax as cj

    rng = np.random.default_rng(seed)
    ground = _surface(*_GROUND, n // 2, rng, seed, faces=("y-",))
    box = {k: _surface(c, s, n // 6, rng, seed + 1 + i) for i, (k, (c, s)) in enumerate(_BOXES.items())}
    return [cj.model.concatenate([ground, box["A"], box["B"], box[k]]) for k in ("C", "D")]


def _cameras(views: int, width: int, height: int):
    """An orbit around the box at radius 4, heights alternating ±0.6, looking at its centre (fov_x 50°)."""
    import cfgs_jax as cj

    cams = []
    for i in range(views):
        a = 2 * np.pi * i / views
        eye = [4.0 * np.sin(a), 0.6 * (-1) ** i, -4.0 * np.cos(a)]
        cams.append(cj.Camera.look_at(eye, [0, 0, 0], up=(0, -1, 0), width=width, height=height, fov_x_deg=50))
    return cams


def _scene(root: Path, g, cams, rng):
    """The date rendered at ``cams`` into ``root/images`` and an ``io.Scene`` over it."""
    from cfgs_jax import splat
    from cfgs_jax.io.colmap import Scene
    from cfgs_jax.io.images import write_image

    (root / "images").mkdir(parents=True, exist_ok=True)
    names = []
    for i, cam in enumerate(cams):
        names.append(f"img_{i:03d}.png")
        out = splat.render(g, cam, statistics=False)  # over black: the colour premultiplied by alpha
        alpha = np.asarray(out.alpha)[..., None]
        rgb = np.asarray(out.image) / np.maximum(alpha, 1e-6)
        write_image(root / "images" / names[-1], np.clip(np.concatenate([rgb, alpha], -1), 0, 1).astype(np.float32))
    pick = rng.choice(len(g), size=min(len(g), 5000), replace=False)
    points = np.asarray(g.means)[pick] + rng.normal(0, 0.01, (len(pick), 3))
    colors = np.clip(np.asarray(g.colors)[pick], 0, 1)
    split = tuple("test" if i % 7 == 3 else "train" for i in range(len(cams)))
    return Scene(root, root / "images", tuple(names), tuple(cams), split, points.astype(np.float32),
                 colors.astype(np.float32))  # fmt: skip


def _configs(args):
    """The stages' configurations: the package defaults, ``--set`` written in, the step counts."""
    import dataclasses

    from cfgs_jax import fusion, train
    from cfgs_jax.config import apply_overrides, check_sections, section

    tables = apply_overrides({"__path__": "bench_fusion_e2e defaults"}, args.set)
    check_sections(tables, ("train", "cross_init", "refine"))
    steps = args.train_steps
    config = dataclasses.replace(
        section(tables, "train", train.TrainConfig),
        steps=steps,
        densify_until=min(15_000, int(0.75 * steps)),
    )
    cross = dataclasses.replace(section(tables, "cross_init", fusion.CrossInitConfig), steps=args.cross_steps)
    refine = dataclasses.replace(section(tables, "refine", fusion.RefineConfig), steps=args.refine_steps)
    return config, cross, refine


def run(args, work: Path, configs) -> dict:
    """Every stage on the two dates under ``work``; ``configs``: training, cross-init and refinement."""
    from cfgs_jax import fusion, train
    from cfgs_jax.fusion.evaluate import evaluate_fused

    width, height = (int(x) for x in args.size.split("x"))
    rng = np.random.default_rng(0)
    cams = _cameras(args.views, width, height)
    t0 = time.perf_counter()
    scenes = [_scene(work / f"d{q}", g, cams, rng) for q, g in enumerate(_dates(args.gaussians))]
    times = {"make_data": time.perf_counter() - t0}
    print(f"make_data {times['make_data']:.1f} s", flush=True)
    config, cross_config, refine_config = configs
    own, models = {}, []
    t0 = time.perf_counter()
    for q, scene in enumerate(scenes):
        fit = train.fit(scene, config, progress=False)
        models.append(fit.gaussians)
        own[f"d{q}"] = {k: fit.metrics[k] for k in ("psnr", "ssim", "lpips")} | {"gaussians": len(fit.gaussians)}
        print(f"train d{q} done at {time.perf_counter() - t0:.1f} s: {own[f'd{q}']}", flush=True)
    times["train"] = time.perf_counter() - t0

    def views(split):
        out = []
        for scene in scenes:
            idx = scene.indices(split)
            out.append(
                fusion.DateViews(
                    tuple(scene.cameras[i] for i in idx), tuple(scene.load_image(int(i), with_alpha=True) for i in idx)
                )
            )
        return out

    train_views, test_views = views("train"), views("test")
    t0 = time.perf_counter()
    model = fusion.merge(models, ["d0", "d1"])
    times["merge"] = time.perf_counter() - t0
    stages = {"merged": evaluate_fused(model, test_views)["dates"]}  # each date's own Gaussians only
    t0 = time.perf_counter()
    model, _ = fusion.cross_init(model, train_views, cross_config)
    times["cross_init"] = time.perf_counter() - t0
    stages["cross_init"] = evaluate_fused(model, test_views)["dates"]
    print(f"cross_init {times['cross_init']:.1f} s", flush=True)
    t0 = time.perf_counter()
    model, report = fusion.refine(
        model,
        train_views,
        refine_config,
        extent=train.scene_extent(scenes[0].cameras),
        train_config=config,
    )
    times["refine"] = time.perf_counter() - t0
    fused = evaluate_fused(model, test_views)
    return {
        "times_s": times,
        "own": own,
        "fused": dict(fused["dates"]) | {"gaussians": len(model.gaussians)},
        "stages": stages,
        "merged_gaussians": sum(o["gaussians"] for o in own.values()),
        "refine_report": {k: report[k] for k in ("steps", "pruned") if k in report},
    }


def markdown(result: dict) -> str:
    a = result["args"]
    t = result["times_s"]
    lines = [
        "# A fusion end to end (data made by the kernel)",
        "",
        f"Machine: {result['machine']}. Date: {result['date']}. Command: `{result['command']}`.",
        f"Two dates at {a['size']}, {a['views']} views each (every 7th a test view), {a['gaussians']:,} true Gaussians; "
        f"training {a['train_steps']:,} steps per date, cross-init {a['cross_steps']:,}, refinement {a['refine_steps']:,}; "
        + (f"changed from the package defaults: {', '.join(a['set'])}." if a.get("set") else "the package defaults."),
        "",
        "| stage | wall time |",
        "|---|---:|",
        *[f"| {k} | {v:.1f} s |" for k, v in t.items()],
        "",
        "Test views of each date (LPIPS: lower is better; a negative PSNR or SSIM margin, or a positive LPIPS",
        "one, means the fused model is worse than the date's own there):",
        "",
        "| date | own model PSNR / SSIM / LPIPS | fused PSNR / SSIM / LPIPS | fused − own PSNR / SSIM / LPIPS |",
        "|---|---|---|---|",
    ]
    for d, o in result["own"].items():
        f = result["fused"][d]
        lines.append(
            f"| {d} | {o['psnr']:.2f} / {o['ssim']:.4f} / {o['lpips']:.4f} | "
            f"{f['psnr']:.2f} / {f['ssim']:.4f} / {f['lpips']:.4f} | "
            f"{f['psnr'] - o['psnr']:+.2f} dB / {f['ssim'] - o['ssim']:+.4f} / {f['lpips'] - o['lpips']:+.4f} |"
        )
    lines += ["", f"Gaussians: {result['merged_gaussians']:,} merged, {result['fused']['gaussians']:,} fused."]
    if "stages" in result:  # where the fused model gains or loses: the same test views after each stage
        lines += [
            "",
            "Each date's test views after each stage, PSNR / SSIM / LPIPS (merged: o = 1 on the date's own Gaussians,",
            "≈ 0 on the other date's, i.e. the own model):",
            "",
            "| date | merged | after cross-init | fused (refined) |",
            "|---|---|---|---|",
        ]
        cells = lambda m: f"{m['psnr']:.2f} / {m['ssim']:.4f} / {m['lpips']:.4f}"
        st = result["stages"]
        for d in result["own"]:
            lines.append(
                f"| {d} | {cells(st['merged'][d])} | {cells(st['cross_init'][d])} | {cells(result['fused'][d])} |"
            )
    return "\n".join(lines) + "\n"


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", default="160x120")
    ap.add_argument("--gaussians", type=int, default=20_000)
    ap.add_argument("--views", type=int, default=28)
    ap.add_argument("--train-steps", type=int, default=1500)
    ap.add_argument("--cross-steps", type=int, default=500)
    ap.add_argument("--refine-steps", type=int, default=1000)
    ap.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="TABLE.KEY=VALUE",
        help="a [train], [cross_init] or [refine] value (repeatable), e.g. refine.lr_alpha=0.05",
    )
    ap.add_argument("--work", type=Path, help="folder for the rendered dates (default: a temporary one)")
    ap.add_argument("--tag", default="")
    args = ap.parse_args()
    configs = _configs(args)  # a wrong --set fails here, before any work
    result = result_header(args)
    with tempfile.TemporaryDirectory() as tmp:
        result |= run(args, args.work or Path(tmp), configs)
    write_result(f"fusion_e2e{args.tag}{backend_suffix()}", result, markdown(result))
    print(markdown(result))
