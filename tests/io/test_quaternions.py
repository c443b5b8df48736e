"""The "smallest three" quaternion form of compressed splat formats (cfgs_jax.io.quaternions)."""

import numpy as np


def test_the_smallest_three_form_gives_back_the_rotation_with_its_largest_component_positive():
    from cfgs_jax.io.quaternions import from_smallest_three, smallest_three

    rng = np.random.default_rng(3)
    q = rng.normal(size=(2000, 4)) * rng.uniform(0.1, 10.0, size=(2000, 1))
    q[:4] = [[0, 0, 0, -2.0], [0, 0.5, 0, 0], [-1, 1e-9, 0, 0], [0.5, -0.5, 0.5, -0.5]]
    largest, others = smallest_three(q)
    assert np.all(np.abs(others) <= np.sqrt(0.5) + 1e-12)
    unit = q / np.linalg.norm(q, axis=1, keepdims=True)
    sign = np.sign(unit[np.arange(len(q)), np.argmax(np.abs(unit), axis=1)])
    np.testing.assert_allclose(from_smallest_three(largest, others), unit * sign[:, None], atol=1e-12)
    assert np.all(from_smallest_three(largest, others)[np.arange(len(q)), largest] > 0)
