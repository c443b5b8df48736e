"""The memory-map guard: compiled executables hold mappings; clearing JAX's caches unmaps them."""

from __future__ import annotations

import sys

import jax
import jax.numpy as jnp
import pytest

from cfgs_jax import compiled_code


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="/proc/self/maps is Linux-only")
def test_compiled_code_holds_mappings_that_clearing_releases():
    f = jax.jit(lambda x: jnp.sin(x) * 2.0 + jnp.sum(x))
    before = compiled_code.map_usage()
    assert before is not None and before[1] > 1000
    for n in range(1, 41):  # 40 executables (one per shape)
        f(jnp.ones(n)).block_until_ready()
    grown = compiled_code.map_usage()[0]
    assert grown - before[0] >= 4 * 40  # several mappings per executable
    assert compiled_code.release_if_near_limit(fraction=0.0)  # "near" any limit: clears
    assert f._cache_size() == 0
    assert compiled_code.map_usage()[0] < grown - 3 * 40
    assert float(f(jnp.ones(3))[0]) == pytest.approx(2 * jnp.sin(1.0) + 3.0)  # recompiles on demand


def test_release_only_above_the_fraction(monkeypatch):
    f = jax.jit(lambda x: x + 1)
    f(jnp.ones(2))
    monkeypatch.setattr(compiled_code, "map_usage", lambda: (1000, 65530))
    assert not compiled_code.release_if_near_limit(0.5) and f._cache_size() == 1
    monkeypatch.setattr(compiled_code, "map_usage", lambda: (40000, 65530))
    assert compiled_code.release_if_near_limit(0.5) and f._cache_size() == 0
    monkeypatch.setattr(compiled_code, "map_usage", lambda: None)  # no /proc: never clears
    f(jnp.ones(2))
    assert not compiled_code.release_if_near_limit(0.0) and f._cache_size() == 1
