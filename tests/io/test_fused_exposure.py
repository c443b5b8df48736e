"""The exposure table through the fused-model files (cfgs_jax.io.fused)."""

import json

import numpy as np

import cfgs_jax as cj
from cfgs_jax.io import read_fused, write_fused

from scenes import exposure_table, model_with_exposure


def test_the_exposure_round_trips_ours_and_folds_into_the_reference_layout(tmp_path):
    table = exposure_table()
    model = model_with_exposure(n=40, exposure=table)
    back = read_fused(write_fused(tmp_path / "ours", model))
    np.testing.assert_allclose(np.asarray(back.exposure), table, rtol=1e-6)  # float32
    np.testing.assert_allclose(np.asarray(cj.light_multipliers(back)), np.asarray(cj.light_multipliers(model)))

    # the authors' layout has l = 2·sigmoid only: the drawn light is stored, clipped at 1.98
    write_fused(tmp_path / "ref", model, layout="reference")
    ref = read_fused(tmp_path / "ref")
    assert ref.exposure is None
    drawn = 2.0 / (1.0 + np.exp(-np.asarray(model.light_logits, np.float64))) * table[np.asarray(model.origin)]
    np.testing.assert_allclose(np.asarray(cj.light_multipliers(ref)), np.minimum(drawn, 1.98), rtol=1e-4)
    meta = json.loads((tmp_path / "ref" / "cfgs_dates.json").read_text())
    assert meta["exposure_folded"]["clipped_channels"] == int(np.sum(drawn > 1.98)) > 0
