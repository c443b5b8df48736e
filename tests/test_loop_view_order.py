"""The view order (cfgs_jax.loop.view_order): a refilled random stack."""

from cfgs_jax import train


def test_view_order_is_a_refilled_random_stack():
    orders = [[train.view_order(7, e * 5 + k, 5) for k in range(5)] for e in range(3)]
    assert all(sorted(o) == list(range(5)) for o in orders) and orders[0] != orders[1]
    assert train.view_order(7, 12, 5) == orders[2][2]
