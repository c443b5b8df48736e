"""The command line's grammar: every subcommand, flag, default, description and example.

``build_parser(prog)`` returns the :mod:`argparse` parser that ``cfgs_jax.app.pipeline.main`` runs; the
commands themselves live in :mod:`cfgs_jax.app.pipeline`. Every flag has help text and shows its default;
every subcommand has a paragraph and an example. Commands that read a run configuration take
``--config`` (a preset name or a TOML path) and any number of ``--set table.key=value`` overrides.
"""

from __future__ import annotations

import argparse
import sys
from importlib import metadata
from pathlib import Path

import jax.numpy as jnp
import numpy as np

from cfgs_jax import viz
from cfgs_jax.app.evaluate import PARTS
from cfgs_jax.errors import InputError
from cfgs_jax.io.formats import FORMATS
from cfgs_jax.synthetic.presets import PRESETS


def version() -> str:
    """The installed distribution's version (``cfgs-jax``), or ``unknown`` outside an install."""
    try:
        return metadata.version("cfgs-jax")
    except metadata.PackageNotFoundError:
        return "unknown"


def program_name(argv0: str | None = None) -> str:
    """How the user called us: ``python -m cfgs_jax.pipeline`` or the console script's name."""
    name = Path(argv0 if argv0 is not None else (sys.argv[0] if sys.argv else "")).name
    if name in ("pipeline.py", "__main__.py", "-c", ""):
        return "python -m cfgs_jax.pipeline"
    return name


class _Formatter(argparse.ArgumentDefaultsHelpFormatter, argparse.RawDescriptionHelpFormatter):
    """Defaults in every flag's help; descriptions and examples keep their line breaks."""

    def _get_help_string(self, action):
        # "(default: None)" / "(default: False)" say nothing: show defaults only where there is one
        if action.default in (None, False, []) or action.default is argparse.SUPPRESS:
            return action.help
        return super()._get_help_string(action)


def _command(sub, name: str, summary: str, description: str, examples: list[str], prog: str):
    """Add subcommand ``name`` with a one-line summary (in the command list), a paragraph and examples."""
    epilog = "example:\n" + "\n".join(f"  {prog} {name} {e}" for e in examples)
    s = sub.add_parser(
        name,
        help=summary,
        description=f"{summary[0].upper()}{summary[1:]}.\n\n{description}",
        epilog=epilog,
        formatter_class=_Formatter,
    )
    s.set_defaults(command=name)
    return s


def _config_args(s, default: str) -> None:
    s.add_argument(
        "--config",
        default=default,
        metavar="PRESET|TOML",
        help="run configuration: a packaged preset (see the `presets` command) or a TOML file",
    )
    _set_arg(
        s,
        "TABLE.KEY=VALUE",
        "override one configuration value, e.g. --set refine.steps=3000 (repeatable; "
        "VALUE is read as TOML, else as a string)",
    )


def _set_arg(s, metavar: str, help: str) -> None:
    """``--set KEY=VALUE`` (repeatable) into ``args.overrides``."""
    s.add_argument("--set", action="append", default=[], metavar=metavar, dest="overrides", help=help)


def _devices_arg(s) -> None:
    s.add_argument(
        "--devices",
        default="all",
        metavar="N|all",
        help="devices the batched stages split their work over (pairs of cross-timestep init, views of a "
        "step with view_batch > 1, rendered views): the first N, or all of every process "
        "(see the README, 'Several devices and hosts')",
    )


def _progress_arg(s) -> None:
    s.add_argument(
        "--no-progress",
        action="store_true",
        help="no progress bars (for logs and batch jobs): a line on each loop's progress every 5 minutes instead",
    )


def _resume_arg(s, what: str) -> None:
    s.add_argument(
        "--resume",
        action="store_true",
        help=f"continue the {what} in --out (without it, an --out holding earlier work is refused)",
    )


def _selection_args(s) -> None:
    s.add_argument("--run", required=True, help="run directory of a finished `fuse`")
    s.add_argument("--t", default="all", help="time selection: one 0/1 per date (1,0,1), date names (d0,d2) or 'all'")
    s.add_argument(
        "--mode",
        choices=("blend", "max", "highlight"),
        default="highlight",
        help="blend: Eq. 4 mean opacity; max: max opacity; highlight: change highlight (Eq. 5)",
    )
    s.add_argument("--grey", action="store_true", help="highlight on a greyscale base (Rec.709 luminance)")
    s.add_argument("--low-contrast", action="store_true", help="highlight on a reduced-contrast base")
    s.add_argument("--max-opacity", action="store_true", help="highlight with the max-opacity blend")
    s.add_argument("--sigma", type=float, default=0.18, help="σ of the persistence filter (Eq. 7)")
    s.add_argument("--contrast", metavar="K,B", help="k,b of the contrast sigmoid (Eq. 8) applied to o (default: none)")
    s.add_argument(
        "--stops",
        help="gradient colours 'r,g,b;r,g,b;...' (linear RGB) or 'rgb' for no remap "
        "(default: the paper's blue-green-red)",
    )


def _add_inspect(sub, prog: str) -> None:
    s = _command(
        sub,
        "inspect",
        "summarise a 3DGS PLY, a fused model or a COLMAP dataset",
        "Prints the number of Gaussians and statistics of their fields (means, scales, opacity, colour), "
        "for a fused model also each date's Gaussians, capture time and mean opacity multiplier o, and "
        "for a COLMAP dataset its images, train/test split and SfM points.",
        ["runs/corals/fused", "point_cloud.ply"],
        prog,
    )
    s.add_argument("path", help="a .ply file, a fused-model directory or a COLMAP dataset (images/ + sparse/0)")


def _add_convert(sub, prog: str) -> None:
    s = _command(
        sub,
        "convert",
        "convert between a 3DGS PLY and the fused-model layouts",
        "A fused model is written in our layout (cfgs: point_cloud.ply + o/l per date) or the authors' "
        "layout (reference: activation.ply + opacity/light arrays); a single-date model or a fused "
        "model's Gaussians as a plain 3DGS PLY.",
        ["runs/corals/fused fused_reference --layout reference", "runs/corals/fused all_dates.ply"],
        prog,
    )
    s.add_argument("src", help="a .ply file or a fused-model directory")
    s.add_argument("dst", help="output .ply file or directory")
    s.add_argument(
        "--layout",
        choices=("cfgs", "reference", "ply"),
        help="output layout (default: ply when DST ends in .ply, else cfgs)",
    )
    s.add_argument("--drop-invalid", action="store_true", help="drop rows with NaN/Inf instead of failing")


def _add_metrics(sub, prog: str) -> None:
    s = _command(
        sub,
        "metrics",
        "PSNR / SSIM / LPIPS between two images or two folders",
        "Folders are matched by file name (stem); the table lists each pair and the mean. Images are "
        "PNG/JPEG (sRGB) or EXR (linear); both of a pair must have one size.",
        ["renders/d0 data/corals/d0/images --json metrics.json"],
        prog,
    )
    s.add_argument("a", help="image file or folder (e.g. renders)")
    s.add_argument("b", help="image file or folder (e.g. ground truth; matched by file name)")
    s.add_argument("--net", choices=("alex", "vgg"), default="alex", help="LPIPS backbone")
    s.add_argument("--json", metavar="FILE", help="also write the numbers to this JSON file")


def _add_synth(sub, prog: str) -> None:

    s = _command(
        sub,
        "synth",
        "render a synthetic multi-date scene with Mitsuba 3",
        "Writes one COLMAP dataset per date (images/ with EXIF capture times, sparse/0) and "
        "ground_truth.json (cameras, date Sim(3)s, which objects change). Needs the `synth` extra "
        '(pip install "cfgs-jax[synth]").',
        ["--preset corals --out data/corals --width 320 --height 240"],
        prog,
    )
    s.add_argument("--preset", required=True, choices=tuple(PRESETS), help="which synthetic scene to render")
    s.add_argument("--out", required=True, help="output folder (one COLMAP dataset per date)")
    s.add_argument("--seed", type=int, default=0, help="random seed of the cameras and scene details")
    s.add_argument("--width", type=int, default=320, help="image width in pixels")
    s.add_argument("--height", type=int, default=240, help="image height in pixels")
    s.add_argument("--images-per-date", type=int, default=32, help="views rendered per date")
    s.add_argument("--spp", type=int, default=32, help="Mitsuba samples per pixel")


def _add_train(sub, prog: str) -> None:
    s = _command(
        sub,
        "train",
        "train one date's 3DGS model from a COLMAP dataset",
        "INRIA 3DGS training (Adam, densification, opacity reset) in JAX. Writes point_cloud.ply, "
        "train.json (losses, test metrics) and INRIA's layout (point_cloud/iteration_N/point_cloud.ply, "
        "cameras.json, cfg_args) so existing 3DGS viewers open the run as it is. -s/-m are INRIA's "
        "names for the dataset and the output.",
        ["-s data/corals/d0 -m runs/d0 --config fast", "--scene data/d0 --out runs/d0 --set train.steps=7000"],
        prog,
    )
    s.add_argument(
        "--scene",
        "-s",
        "--source-path",
        dest="scene",
        required=True,
        help="COLMAP dataset of one date (images/ + sparse/0)",
    )
    s.add_argument(
        "--out",
        "-m",
        "--model-path",
        dest="out",
        required=True,
        help="output directory (point_cloud.ply, train.json, checkpoint, INRIA layout)",
    )
    _config_args(s, "paper")
    s.add_argument(
        "--resolution",
        "-r",
        type=int,
        default=1,
        metavar="N",
        help="train on images downscaled by N (1, 2, 4, 8; cameras scaled to match), as INRIA's -r",
    )
    s.add_argument("--steps", type=int, help="number of steps (the densification schedule is scaled to it)")
    s.add_argument("--continue-from", metavar="PLY", help="train this model --steps more steps without densification")
    _resume_arg(s, "training")
    s.add_argument("--seed", type=int, help="random seed (default: [train] seed)")
    s.add_argument(
        "--sh-degree",
        type=int,
        choices=(0, 1, 2, 3),
        help="view-dependent colour: the SH degree trained, one band more every [train] sh_interval steps "
        "(default: [train] sh_degree, 3 as INRIA's; 0: view-independent colour; the PLY keeps the "
        "coefficients, INRIA's f_rest; with --continue-from: the model's degree)",
    )
    s.add_argument(
        "--stop-after", type=int, metavar="STEP", help="stop (with a checkpoint) after this many total steps"
    )
    s.add_argument("--eval-every", type=int, metavar="N", help="also evaluate on the test split every N steps")
    s.add_argument("--no-eval", action="store_true", help="skip the test-split evaluation at the end")
    s.add_argument("--lpips-net", choices=("alex", "vgg"), default="alex", help="LPIPS backbone of the evaluation")
    _progress_arg(s)
    _devices_arg(s)


def _add_fuse(sub, prog: str) -> None:
    s = _command(
        sub,
        "fuse",
        "fuse per-date datasets into one multi-temporal model",
        "Trains each date (or takes --models), registers the dates to the first by SfM and Sim(3) "
        "(or takes --transforms), merges, runs cross-timestep initialisation (Eq. 2-3) and joint "
        "refinement (Eq. 4-6). Dates are fused in capture-time order (--captured or the images' EXIF). "
        "Each stage is checkpointed: an interrupted run continues with --resume.",
        [
            "--dates data/corals/d0 data/corals/d1 data/corals/d2 --out runs/corals --config fast",
            "--dates A B --models A.ply B.ply --transforms sim3.json --out runs/ab --set refine.steps=3000",
        ],
        prog,
    )
    s.add_argument(
        "--dates",
        nargs="+",
        required=True,
        metavar="DATASET",
        help="per-date COLMAP datasets (the earliest is the reference frame)",
    )
    s.add_argument("--out", required=True, help="run directory")
    _config_args(s, "paper")
    s.add_argument("--models", nargs="+", metavar="PLY", help="trained per-date PLYs (default: train them in the run)")
    s.add_argument("--transforms", metavar="JSON", help="known date → reference Sim(3)s (skips SfM registration)")
    s.add_argument(
        "--captured",
        nargs="+",
        metavar="DATE",
        help="capture time of each --dates entry (ISO 8601, same order; default: the images' EXIF)",
    )
    s.add_argument(
        "--resolution",
        "-r",
        type=int,
        default=1,
        metavar="N",
        help="use images downscaled by N (cameras scaled to match)",
    )
    s.add_argument("--drop-invalid", action="store_true", help="drop --models rows with NaN/Inf instead of failing")
    _resume_arg(s, "fusion run")
    _progress_arg(s)
    _devices_arg(s)


def _add_extend(sub, prog: str) -> None:
    s = _command(
        sub,
        "extend",
        "add one date to a finished fusion run (incremental fusion)",
        "Registers the new date, initialises only the pairs that involve it (cross-timestep init "
        "restricted to the new date) and refines the whole model; the date is inserted at its place "
        "in time. The run directory is updated in place.",
        ["--run runs/corals --date data/corals/d3"],
        prog,
    )
    s.add_argument("--run", required=True, help="run directory of a finished `fuse` (updated in place)")
    s.add_argument("--date", required=True, metavar="DATASET", help="the new date's COLMAP dataset")
    s.add_argument("--model", metavar="PLY", help="its trained PLY (default: train it in the run)")
    s.add_argument("--transforms", metavar="JSON", help="the new date's date → reference Sim(3) (skips registration)")
    s.add_argument("--captured", metavar="DATE", help="its capture time (ISO 8601; default: its images' EXIF)")
    s.add_argument("--resume", action="store_true", help="continue an interrupted extension of --run by this date")
    _progress_arg(s)
    _devices_arg(s)


def _add_compact(sub, prog: str) -> None:
    s = _command(
        sub,
        "compact",
        "merge the copies of persistent surfaces in a fused run (cross-timestep pruning)",
        "Finds Gaussians of different dates that draw the same unchanged surface (overlapping, alike, "
        "present at the same dates), merges each group into one, and refines briefly to recover. The "
        "run is updated in place; the model before is kept in RUN/before_compact and the report "
        "(Gaussians and test PSNR/SSIM/LPIPS before and after, per date) is RUN/compact.json. The "
        "criteria are the [compact] table of the run's configuration.",
        ["--run runs/corals", "--run runs/corals --set compact.max_distance=0.3 --set compact.refine_steps=1000"],
        prog,
    )
    s.add_argument("--run", required=True, help="run directory of a finished `fuse` (updated in place)")
    _set_arg(s, "compact.KEY=VALUE", "override one [compact] value of the run's configuration (repeatable)")
    _progress_arg(s)


def _add_changes(sub, prog: str) -> None:
    s = _command(
        sub,
        "changes",
        "find what changed between two dates of a fused run: masks, changed Gaussians, regions",
        "Scores every Gaussian by how much better the other date's training images are explained "
        "without it than with it (a brightness gain allowed, so light and shadow are not change), "
        "pooled over its nearest neighbours. Writes DIR/masks/<date>/<image>.png (255 = changed) and "
        "DIR/scores/<date>/<image>.png for the test views of both dates, DIR/changed.ply (the changed "
        "Gaussians, 3DGS PLY) and DIR/regions.json / regions.md (changed regions in 3D and per view). "
        "The detector's values are the [changes] table of the run's configuration.",
        [
            "--run runs/corals --pair d0,d2 --out changes/d0_d2",
            "--run runs/corals --pair d1,d3 --out ch --set changes.threshold=0.08",
        ],
        prog,
    )
    s.add_argument("--run", required=True, help="run directory of a finished `fuse` (read only)")
    s.add_argument("--pair", required=True, metavar="DATE,DATE", help="the two dates, by name (or index)")
    s.add_argument("--out", required=True, help="output directory")
    s.add_argument(
        "--split", default="test", choices=["test", "train", "all"], help="which views of both dates get masks"
    )
    _set_arg(
        s,
        "changes.KEY=VALUE",
        "override one [changes] or [render] value of the run's configuration, e.g. render.backend=warp (repeatable)",
    )
    _progress_arg(s)


def _add_eval(sub, prog: str) -> None:

    s = _command(
        sub,
        "eval",
        "the paper's evaluation protocol on one scene, plus change detection",
        "Individual, merged and fused models at N refinement steps (and ablations), PSNR/SSIM/LPIPS on "
        "each date's test views, change detection against ground truth. Writes table.md/json, "
        "figure.png and change_pr.png.",
        [
            "--scene corals --config eval --out runs/eval_corals",
            "--scene corals --config benchmarks/eval_small.toml --out runs/eval_small --resume",
            "--scene flood --config benchmarks/eval_large.toml --out runs/flood --part individual --dates d0 --resume",
        ],
        prog,
    )
    s.add_argument(
        "--scene", required=True, help=f"a synthetic preset ({', '.join(PRESETS)}) or a folder of per-date datasets"
    )
    _config_args(s, "fast")
    s.add_argument("--out", required=True, help="output folder")
    s.add_argument(
        "--part",
        choices=PARTS,
        default="all",
        help="run one part of the protocol only, so that processes sharing --out run parts side by side: "
        "train (the per-date models), then fusion, individual (Individual +N), known_transforms, and "
        "ablations once the fusion's cross-init is done; 'all' (default) runs what is left and writes the table",
    )
    s.add_argument("--dates", nargs="+", metavar="DATE", help="with --part individual: these dates only")
    _resume_arg(s, "evaluation")
    _progress_arg(s)
    _devices_arg(s)


def _add_sweep(sub, prog: str) -> None:
    s = _command(
        sub,
        "sweep",
        "ablation sweep: a base configuration and a grid of overrides",
        "Runs every combination of the [sweep.grid] values on one scene, sharing the trained and "
        "registered dates; writes sweep.md/json and sweep.png.",
        ["--config sweep_fast --out runs/sweep"],
        prog,
    )
    s.add_argument(
        "--config",
        required=True,
        metavar="PRESET|TOML",
        help="sweep file ([sweep] scene, base, [sweep.grid]), e.g. the preset sweep_fast",
    )
    s.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="TABLE.KEY=VALUE",
        dest="overrides",
        help="override a value of the base configuration for every variant (repeatable)",
    )
    s.add_argument("--out", required=True, help="output folder")
    _resume_arg(s, "sweep (finished variants are skipped)")
    _progress_arg(s)


def _add_render(sub, prog: str) -> None:
    s = _command(
        sub,
        "render",
        "render a time selection or change highlight of a fused run",
        "Renders the selected dates (Eq. 4 blend, max opacity, or the change highlight of Eq. 5-8) at "
        "the test cameras or along an orbit; writes PNG (sRGB, with a legend) and EXR (linear) per view, "
        "and for an orbit also orbit.mp4.",
        [
            "--run runs/corals --t d0,d2 --mode highlight --grey --out renders/d0_d2",
            "--run runs/corals --cameras orbit --frames 48 --out renders/orbit",
        ],
        prog,
    )
    _selection_args(s)
    s.add_argument("--cameras", choices=("test", "orbit"), default="test", help="which views")
    s.add_argument("--frames", type=int, default=24, help="number of orbit views")
    s.add_argument("--width", type=int, help="orbit image width (default: the training cameras')")
    s.add_argument("--height", type=int, help="orbit image height (default: the training cameras')")
    s.add_argument("--fps", type=int, default=12, help="frame rate of orbit.mp4")
    s.add_argument("--background", default="0,0,0", help="r,g,b in [0, 1]")
    s.add_argument("--out", required=True, help="output folder")
    _progress_arg(s)
    _devices_arg(s)


def _add_export(sub, prog: str) -> None:
    s = _command(
        sub,
        "export",
        "bake a time selection or highlight into a splat file (PLY, SPZ, compressed PLY, SOG)",
        "The file holds each Gaussian's opacity and colour as seen under the selection, so any 3DGS viewer "
        "shows it. Blend and max keep the model's SH (view-dependent colour); a highlight is written "
        "DC-only, from each Gaussian's colour averaged over view directions (render draws it per view). "
        "ply is exact (float32); spz (Niantic SPZ v4), compressed-ply (SuperSplat's) and sog (PlayCanvas SOG "
        "v2) quantise each field and are several times smaller.",
        [
            "--run runs/corals --t d0,d2 --mode highlight --out highlight.ply",
            "--run runs/corals --t all --mode blend --out corals.spz",
            "--run runs/corals --t d1 --mode blend --out d1.sog",
            "--run runs/corals --format web --out corals_page",
        ],
        prog,
    )
    _selection_args(s)
    s.add_argument("--out", required=True, help="output file (.ply, .spz, .compressed.ply, .sog), or folder (web)")
    s.add_argument(
        "--format",
        choices=sorted(FORMATS) + ["web"],
        help="file format (default: from the suffix of --out); web: a folder with a static page (index.html) "
        "that toggles dates, blend / max and the highlight in any browser (--t and --mode are ignored)",
    )
    _progress_arg(s)
    s.add_argument("--sh-degree", type=int, help="SH degree written (default: the model's; lower drops bands)")


def _add_view(sub, prog: str) -> None:
    s = _command(
        sub,
        "view",
        "browser viewer of a fused run (viser; 127.0.0.1 only)",
        "A time slider per date, the highlight controls and the camera of each view. Needs the "
        '`viewer` extra (pip install "cfgs-jax[viewer]").',
        ["--run runs/corals --port 8080"],
        prog,
    )
    s.add_argument("--run", required=True, help="run directory of a finished `fuse`")
    s.add_argument("--port", type=int, default=8080, help="port on 127.0.0.1")


def _add_presets(sub, prog: str) -> None:
    s = _command(
        sub,
        "presets",
        "list the packaged run configurations, or print one",
        "Without a name, lists the presets with their leading comment. With a name, prints the "
        "TOML (or writes it to --out) as a starting point for your own configuration.",
        ["", "paper --out my_config.toml"],
        prog,
    )
    s.add_argument("name", nargs="?", help="preset to print")
    s.add_argument("--out", help="write the preset to this file instead of printing it")


def _add_demo(sub, prog: str) -> None:
    s = _command(
        sub,
        "demo",
        "the embedded default job: synthesise, train, fuse, render, tabulate",
        "The whole pipeline on a small synthetic corals scene: renders the dates with Mitsuba, trains "
        "one model per date, registers and fuses them, renders each date and a change highlight, and "
        "tabulates each date's test metrics before and after fusion (summary.md).",
        ["--out runs/demo", "--out runs/demo4 --dates 4 --width 320 --height 240"],
        prog,
    )
    s.add_argument("--out", default="runs/demo", help="output folder")
    _config_args(s, "demo")
    s.add_argument("--dates", type=int, default=2, help="how many dates of the corals scene to fuse (2-4)")
    s.add_argument("--width", type=int, default=160, help="image width in pixels")
    s.add_argument("--height", type=int, default=120, help="image height in pixels")
    s.add_argument("--images-per-date", type=int, default=12, help="views rendered per date")
    _resume_arg(s, "demo")
    _progress_arg(s)


def build_parser(prog: str | None = None) -> argparse.ArgumentParser:
    """The full parser; ``prog`` defaults to how the program was called."""
    prog = prog or program_name()
    p = argparse.ArgumentParser(
        prog=prog,
        formatter_class=_Formatter,
        description="cfgs_jax: fuse per-date 3D Gaussian Splatting models into one multi-temporal model "
        "(ChronoFuseGS) and render any time selection with change highlighting.",
        epilog=f"quick start:\n  {prog} demo --out runs/demo\n"
        f"  {prog} synth --preset corals --out data/corals\n"
        f"  {prog} fuse --dates data/corals/d0 data/corals/d1 --out runs/corals --config fast\n"
        f"  {prog} render --run runs/corals --t d0,d1 --mode highlight --out renders/\n"
        f"run `{prog} COMMAND --help` for a command's flags and an example.",
    )
    p.add_argument("--version", action="version", version=f"%(prog)s {version()}")
    p.add_argument("-v", "--verbose", action="store_true", help="log progress and notes")
    sub = p.add_subparsers(dest="command", required=True, metavar="COMMAND")

    for add in (
        _add_inspect,
        _add_convert,
        _add_metrics,
        _add_synth,
        _add_train,
        _add_fuse,
        _add_extend,
        _add_compact,
        _add_changes,
        _add_eval,
        _add_sweep,
        _add_render,
        _add_export,
        _add_view,
        _add_presets,
        _add_demo,
    ):
        add(sub, prog)
    return p


def parse_selection(text: str, names: list[str]) -> np.ndarray:
    """``"1,0,1"`` (one 0/1 per date), ``"all"`` or date names ``"d0,d2"`` → binary t."""
    text = text.strip()
    if text == "all":
        return np.ones(len(names))
    parts = [p.strip() for p in text.split(",") if p.strip()]
    if parts and all(p in names for p in parts):
        return np.asarray([float(n in parts) for n in names])
    try:
        t = np.asarray([float(p) for p in parts])
    except ValueError:
        raise InputError(
            f"cannot read {text!r}",
            field="--t",
            fix=f"give one 0/1 per date ({len(names)}), 'all', or date names from {names}",
        ) from None
    if len(t) != len(names):
        raise InputError(f"{len(t)} entries for {len(names)} dates {names}", field="--t", fix="give one 0/1 per date")

    viz.normalize_selection(t)  # binary, not all zero
    return t


def parse_stops(text: str | None):
    """``"r,g,b;r,g,b;..."`` (linear RGB), ``"rgb"`` for the full-RGB filter, or None for the default."""

    if text is None:
        return viz.DEFAULT_STOPS
    if text.strip().lower() == "rgb":
        return None
    try:
        stops = tuple(tuple(float(v) for v in s.split(",")) for s in text.split(";"))
    except ValueError:
        raise InputError(f"cannot read {text!r}", field="--stops", fix="write colours as r,g,b;r,g,b;...") from None
    viz.remap_to_gradient(jnp.ones(3), stops)  # validates
    return stops
