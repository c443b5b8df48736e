"""The float64 reference kernel (cfgs_jax.splat.reference) against central differences."""

import jax
import numpy as np
from kernel_cases import NAMES, reference_gradients


def test_reference_gradients_match_central_differences(grad_case):
    """Float64 reference autodiff vs central finite differences along random directions (rel ≤ 1e-3)."""
    g, om, cm, cam, w_img, w_a = grad_case
    f, args, _, grads = reference_gradients(g, om, cm, cam, w_img, w_a)
    rng = np.random.default_rng(3)
    with jax.enable_x64(True):
        leaves, treedef = jax.tree_util.tree_flatten(args)
        for i, name in enumerate(NAMES):
            for _ in range(2):
                v = rng.normal(size=leaves[i].shape)
                h = 1e-6

                def at(s, i=i, v=v):
                    moved = list(leaves)
                    moved[i] = leaves[i] + s * h * v
                    return float(f(*jax.tree_util.tree_unflatten(treedef, moved)))

                fd = (at(1) - at(-1)) / (2 * h)
                ad = float(np.sum(grads[i] * v))
                assert abs(fd - ad) <= 1e-3 * max(abs(ad), 1e-6), (name, fd, ad)
