"""Sizes and round-trip errors of the export formats (``export --format``), per field, with the render
error they cause, on fused runs and model files.

    python benchmarks/bench_export_formats.py --run runs/demo/run --ply tests/data/real_3dgs_donut_dc_only.ply
    python benchmarks/bench_export_formats.py ... --external   # also splat-transform's decoding (tools/npm)

For a run, the model is the blend of all its dates baked as ``export --mode blend`` bakes it (the
model's SH degree); a PLY is taken as it is. Each format is written, read back with our reader, and
compared row by row (the file's order) with the model: the largest and RMS error of the position (as a
share of the scene's extent), the DC colour (in 1/255; colours beyond a format's range are counted
apart), the log scale, the opacity α, the rotation (degrees between the two rotations) and the SH
coefficients; and the PSNR of renders of the read-back model against the exact one at the run's test
views (up to 4) or, for a PLY, at four views around it. With ``--external`` the files are also
decoded by PlayCanvas ``splat-transform`` and its largest difference from our decoding is reported.
Writes results/export_formats.md and .json.
"""

from __future__ import annotations

import argparse
import datetime
import json
import shlex
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import RESULTS, machine

from cfgs_jax import splat, viz
from cfgs_jax.app.render_run import open_run
from cfgs_jax.io.formats import FORMATS, read_gaussians, write_gaussians
from cfgs_jax.io.ply import channel_major, read_ply
from cfgs_jax.model import SH_C0, Camera, Gaussians, select

REPO = Path(__file__).resolve().parents[1]
CLI = REPO / "tools" / "npm" / "node_modules" / "@playcanvas" / "splat-transform" / "bin" / "cli.mjs"
#: The DC colour range each format holds (beyond it values are clamped); None: unbounded.
COLOUR_RANGE = {"spz": SH_C0 * 127.5 / (0.15 * 255), "ply": None, "compressed-ply": None, "sog": None}
#: The log-scale range each format holds (SPZ: (s + 10)·16 in a byte; compressed PLY clamps to ±20).
SCALE_RANGE = {"spz": (-10.0, 255 / 16 - 10.0), "ply": None, "compressed-ply": (-20.0, 20.0), "sog": None}


def _rotation_degrees(a, b) -> np.ndarray:
    """The angle between the rotations of unit-normalised quaternions a and b: |a ∓ b| = 2 sin(θ/4)
    (stable near 0, unlike an arccos of their dot product)."""
    a = np.asarray(a, np.float64) / np.linalg.norm(a, axis=1, keepdims=True)
    b = np.asarray(b, np.float64) / np.linalg.norm(b, axis=1, keepdims=True)
    chord = np.minimum(np.linalg.norm(a - b, axis=1), np.linalg.norm(a + b, axis=1))
    return np.degrees(4 * np.arcsin(np.clip(chord / 2, 0, 1)))


def _stats(err: np.ndarray) -> tuple[float, float]:
    err = np.abs(np.asarray(err, np.float64)).reshape(-1)
    return (float(err.max()), float(np.sqrt(np.mean(err**2)))) if err.size else (0.0, 0.0)


def _orbit(g: Gaussians, count: int = 4, size=(160, 120)) -> list[Camera]:
    means = np.asarray(g.means, np.float64)
    centre, radius = np.median(means, 0), np.percentile(np.linalg.norm(means - np.median(means, 0), axis=1), 90)
    cams = []
    for k in range(count):
        angle = 2 * np.pi * k / count
        eye = centre + 2.2 * radius * np.array([np.cos(angle), np.sin(angle), 0.6])
        cams.append(Camera.look_at(eye, centre, width=size[0], height=size[1], fov_x_deg=50.0))
    return cams


def _psnr(a: Gaussians, b: Gaussians, cameras) -> float:
    errs = []
    for cam in cameras:
        x = np.clip(np.asarray(splat.render(a, cam).image), 0, 1)
        y = np.clip(np.asarray(splat.render(b, cam).image), 0, 1)
        errs.append(np.mean((x - y) ** 2))
    return float(10 * np.log10(1 / max(np.mean(errs), 1e-12)))


def _external(path: Path, fmt: str, ours: Gaussians) -> float:
    """Largest difference between splat-transform's decoding of ``path`` and ours (over x, y, z, the
    log scales, the DC colour, the unit quaternion and the SH coefficients)."""
    import plyfile

    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "back.ply"
        subprocess.run(["node", str(CLI), "-q", "-w", str(path), str(out)], check=True)
        v = plyfile.PlyData.read(str(out))["vertex"].data
    cols = lambda names: np.stack([np.asarray(v[k], np.float64) for k in names], 1)
    diffs = [
        np.abs(cols("xyz") - ours.means).max(),
        np.abs(cols([f"scale_{i}" for i in range(3)]) - ours.log_scales).max(),
        np.abs(0.5 + SH_C0 * cols([f"f_dc_{i}" for i in range(3)]) - ours.colors).max(),
        _rotation_degrees(cols([f"rot_{i}" for i in range(4)]), ours.quats).max() / 180,
    ]
    if ours.sh_rest is not None:
        rest = [f"f_rest_{i}" for i in range(3 * ours.sh_rest.shape[1])]
        diffs.append(np.abs(cols(rest) - channel_major(np.asarray(ours.sh_rest))).max())
    return float(max(diffs))


def measure(name: str, g: Gaussians, cameras, external: bool) -> list[dict]:
    """One row per format for the model ``g`` called ``name``."""
    rows = []
    extent = float(np.max(np.ptp(np.asarray(g.means), axis=0)))
    with tempfile.TemporaryDirectory() as tmp:
        ply_size = None
        for fmt, (suffix, _, what) in FORMATS.items():
            path = Path(tmp) / f"model{suffix}"
            start = time.perf_counter()
            _, order = write_gaussians(path, g, fmt)
            seconds = time.perf_counter() - start
            back = read_gaussians(path, fmt)
            ref = select(g, order)
            size = path.stat().st_size
            ply_size = ply_size or size
            c_ref, c_back = np.asarray(ref.colors, np.float64), np.asarray(back.colors, np.float64)
            bound = COLOUR_RANGE[fmt]
            inside = np.ones(c_ref.shape, bool) if bound is None else np.abs(c_ref - 0.5) <= bound
            s_ref, s_back = np.asarray(ref.log_scales, np.float64), np.asarray(back.log_scales, np.float64)
            s_range = SCALE_RANGE[fmt]
            s_in = np.ones(s_ref.shape, bool) if s_range is None else (s_ref >= s_range[0]) & (s_ref <= s_range[1])
            alpha = lambda x: 1 / (1 + np.exp(-np.asarray(x.opacity_logits, np.float64)))
            row = {
                "model": name,
                "format": fmt,
                "what": what,
                "gaussians": len(g),
                "sh_degree": g.sh_degree,
                "bytes": size,
                "ratio_to_ply": size / ply_size,
                "write_s": seconds,
                "position": [v / extent for v in _stats(np.asarray(back.means) - np.asarray(ref.means))],
                "colour_255": [255 * v for v in _stats((c_back - c_ref)[inside])],
                "colour_clamped_share": float(1 - inside.mean()),
                "log_scale": list(_stats((s_back - s_ref)[s_in])),
                "log_scale_clamped_share": float(1 - s_in.mean()),
                "alpha_255": [255 * v for v in _stats(alpha(back) - alpha(ref))],
                "rotation_deg": list(_stats(_rotation_degrees(back.quats, ref.quats))),
                "sh": list(_stats(np.asarray(back.sh_rest) - np.asarray(ref.sh_rest))) if g.sh_degree else None,
                "render_psnr": _psnr(back, ref, cameras) if fmt != "ply" else float("inf"),
            }
            if external and fmt != "ply":
                row["splat_transform_max_diff"] = _external(path, fmt, back)
            rows.append(row)
            print(json.dumps(row), flush=True)
    return rows


def _fmt(pair, digits=3) -> str:
    return "–" if pair is None else f"{pair[0]:.{digits}g} / {pair[1]:.{digits}g}"


def table(rows: list[dict], command: str) -> str:
    date = datetime.date.today().isoformat()
    lines = [
        "# Export formats: sizes and round-trip errors (bench_export_formats.py)",
        "",
        f"Command: `{command}`. Machine: {machine()}. Date: {date}. Each model written in every format, read back "
        "with our reader and compared row by row; errors as largest / RMS. Position: a share of the scene's largest "
        "extent. DC colour in 1/255, over the colours inside the format's range (SPZ holds 0.5 ± 0.94; the share "
        "beyond is clamped and counted apart; so are log scales beyond SPZ's [−10, 5.94]). Rotation: degrees between the rotations. Render PSNR: the read-back "
        "model against the exact one at the run's test views (up to 4) or four views around a PLY model."
        + (" splat-transform: the largest difference between its decoding and ours." if "splat_transform_max_diff" in str(rows) else ""),
        "",
        "| model | format | Gaussians (SH) | size | × PLY | write s | position | DC colour /255 (clamped) | log scale (clamped) | α /255 | rotation ° | SH | render PSNR dB |"
        + (" splat-transform diff |" if "splat_transform_max_diff" in str(rows) else ""),
        "|---|---|---:|---:|---:|---:|---|---|---|---|---|---|---:|" + ("---:|" if "splat_transform_max_diff" in str(rows) else ""),
    ]  # fmt: skip
    for r in rows:
        clamp = f" ({100 * r['colour_clamped_share']:.2f} %)" if r["colour_clamped_share"] else ""
        s_clamp = f" ({100 * r['log_scale_clamped_share']:.2f} %)" if r["log_scale_clamped_share"] else ""
        psnr = "exact" if r["render_psnr"] == float("inf") else f"{r['render_psnr']:.1f}"
        line = (
            f"| {r['model']} | {r['format']} | {r['gaussians']:,} ({r['sh_degree']}) | {r['bytes'] / 1e6:.2f} MB | "
            f"{r['ratio_to_ply']:.3f} | {r['write_s']:.2f} | {_fmt(r['position'])} | {_fmt(r['colour_255'])}{clamp} | "
            f"{_fmt(r['log_scale'])}{s_clamp} | {_fmt(r['alpha_255'])} | {_fmt(r['rotation_deg'])} | {_fmt(r['sh'])} | "
            f"{psnr} |"
        )
        if "splat_transform_max_diff" in str(rows):
            line += f" {r.get('splat_transform_max_diff', 0.0):.2g} |"
        lines.append(line)
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--run", action="append", default=[], help="a fused run (its blend of all dates)")
    p.add_argument("--ply", action="append", default=[], help="a 3DGS PLY model")
    p.add_argument("--external", action="store_true", help="also decode with splat-transform (tools/npm)")
    p.add_argument("--name", default="export_formats", help="results/NAME.md and .json")
    args = p.parse_args(argv)
    rows = []
    for run_dir in args.run:
        run = open_run(run_dir)
        g = viz.bake(run.model, np.ones(len(run.names), np.float32), mode="mean")
        cameras = [c for _, c in run.test_cameras()[:4]]
        rows += measure(f"{Path(run_dir).parent.name}/{Path(run_dir).name}", g, cameras, args.external)
    for ply in args.ply:
        g = read_ply(ply)
        rows += measure(Path(ply).name, g, _orbit(g), args.external)
    command = "python benchmarks/bench_export_formats.py " + shlex.join(sys.argv[1:] if argv is None else argv)
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / f"{args.name}.md").write_text(table(rows, command))
    (RESULTS / f"{args.name}.json").write_text(json.dumps({"command": command, "rows": rows}, indent=1))
    print(table(rows, command))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
