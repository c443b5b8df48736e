"""Adding a date (cfgs_jax.fusion.fuse.add_date) at its place in time."""

import dataclasses

import jax.numpy as jnp
import numpy as np

import cfgs_jax as cj
from cfgs_jax import fusion

from scenes import blobs


def test_add_date_inserts_a_date_at_its_place_in_time():
    """``add_date(position=1)`` into a two-date model: o and l columns are inserted (old columns
    unchanged), origins at or after 1 move up, the new Gaussians are own at 1, other dates ≈ 0."""
    a, b, c = blobs([[0, 0, 0]]), blobs([[1, 0, 0], [2, 0, 0]]), blobs([[3, 0, 0]])
    m = fusion.merge([a, c], ["jan", "jul"])
    m = dataclasses.replace(
        m,
        o_logits=jnp.asarray([[1.0, 2.0], [3.0, 4.0]]),
        light_logits=jnp.arange(12, dtype=jnp.float32).reshape(2, 2, 3),
    )
    out = fusion.add_date(m, b, cj.DateInfo("apr", captured="2024-04-15"), position=1)
    o = np.asarray(out.o_logits)
    assert [d.name for d in out.dates] == ["jan", "apr", "jul"] and out.dates[1].captured == "2024-04-15"
    np.testing.assert_array_equal(o[:2, [0, 2]], [[1.0, 2.0], [3.0, 4.0]])
    assert np.all(o[:2, 1] == fusion.OTHER_LOGIT) and np.all(o[2:, 1] == fusion.OWN_LOGIT)
    assert np.all(o[2:, [0, 2]] == fusion.OTHER_LOGIT)
    np.testing.assert_array_equal(np.asarray(out.light_logits)[:2, [0, 2]], np.asarray(m.light_logits))
    assert not np.any(np.asarray(out.light_logits)[:, 1]) and not np.any(np.asarray(out.light_logits)[2:])
    assert np.asarray(out.origin).tolist() == [0, 2, 1, 1]
    np.testing.assert_array_equal(np.asarray(out.gaussians.means)[2:], np.asarray(b.means))
