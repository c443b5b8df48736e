"""The exposure table of a model (cfgs_jax.model.light_multipliers): each Gaussian lit by its origin's
exposure."""

import dataclasses

import numpy as np
import pytest

import cfgs_jax as cj
from cfgs_jax import fusion

from scenes import exposure_table, model_with_exposure


def test_light_multipliers_apply_the_exposure_of_each_gaussians_origin():
    table = exposure_table()
    model = model_with_exposure(exposure=table)
    logits, origin = np.asarray(model.light_logits, np.float64), np.asarray(model.origin)
    want = 2.0 / (1.0 + np.exp(-logits)) * table[origin]  # [N, T, 3], row i: its origin's gains
    np.testing.assert_allclose(np.asarray(cj.light_multipliers(model)), want, rtol=1e-5)
    plain = dataclasses.replace(model, exposure=None)
    np.testing.assert_allclose(np.asarray(cj.light_multipliers(plain)), 2.0 / (1.0 + np.exp(-logits)), rtol=1e-5)

    # selecting dates keeps their block of the table; adding a date inserts a row and a column of ones
    sub = cj.select_dates(model, [2, 0])
    np.testing.assert_allclose(np.asarray(sub.exposure), table[np.ix_([2, 0], [2, 0])])
    grown = fusion.add_date(model, model_with_exposure(n=2, t=1, seed=3).gaussians, "new", position=1)
    got = np.asarray(grown.exposure)
    np.testing.assert_allclose(got[[0, 2, 3]][:, [0, 2, 3]], table)
    assert np.all(got[1] == 1.0) and np.all(got[:, 1] == 1.0)
    np.testing.assert_allclose(np.asarray(cj.light_multipliers(grown))[: len(model)][:, [0, 2, 3]], want, rtol=1e-5)

    with pytest.raises(cj.InputError, match="exposure"):
        model_with_exposure(exposure=np.ones((3, 2, 3)))
    with pytest.raises(cj.InputError, match="positive"):
        model_with_exposure(exposure=-table)
    with pytest.raises(cj.InputError, match="exposure tables"):
        cj.concatenate([model, plain])
