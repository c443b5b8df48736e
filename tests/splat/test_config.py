"""The rasteriser's configuration (cfgs_jax.splat.config): INRIA's defaults, every refused value named
by its ``[render]`` key, and which sub-tile side and backend a setting resolves to."""

import dataclasses

import pytest

from cfgs_jax.errors import InputError
from cfgs_jax.splat import RenderConfig


def test_the_defaults_are_inrias_rasteriser():
    """Near plane 0.2, 16-pixel tiles, the 0.3 px² low-pass, the frustum clamp 1.3, α in [1/255, 0.99] and
    the early stop at T < 1e-4: the constants of INRIA's ``forward.cu`` / ``auxiliary.h``."""
    c = RenderConfig()
    assert (c.near, c.tile_size, c.eps2d, c.clamp_fov) == (0.2, 16, 0.3, 1.3)
    assert (c.min_alpha, c.max_alpha, c.min_transmittance) == (1.0 / 255.0, 0.99, 1e-4)
    assert c.capacity is None and c.tile_cull and c.resolved_backend() == "xla"


@pytest.mark.parametrize(
    ("change", "field", "words"),
    [
        ({"tile_size": 0}, "render.tile_size", "positive integer"),
        ({"tile_size": 2.5}, "render.tile_size", "positive integer"),
        ({"chunk": -4}, "render.chunk", "positive integer"),
        ({"subtile": 6}, "render.subtile", "divisor of tile_size (16)"),
        ({"subtile": 8, "tile_cull": False}, "render.subtile", "exact tile culling"),
        ({"tile_batch": 0}, "render.tile_batch", "positive integer or unset"),
        ({"capacity": -1}, "render.capacity", "positive integer or unset"),
        ({"backend": "cuda"}, "render.backend", "unknown backend 'cuda'"),
        ({"num_warps": 3}, "render.num_warps", "1, 2, 4, 8 or 16"),
        ({"scatter": "relaxed"}, "render.scatter", "unknown scatter"),
        ({"walk": "diagonal"}, "render.walk", "unknown walk"),
        ({"near": 0.0}, "near", ""),
        ({"eps2d": -0.1}, "eps2d", ""),
        ({"min_alpha": 1.0}, "min_alpha", ""),
    ],
)
def test_a_refused_value_names_its_key(change, field, words):
    """Each value the kernel cannot use is refused at construction, naming its key (and the rule)."""
    with pytest.raises(InputError) as err:
        RenderConfig(**change)
    assert field in str(err.value) and words in str(err.value)


def test_the_sub_tile_side_and_backend_resolve_as_documented():
    """Unset: half the tile on the XLA backend with the exact cull (an even tile), the whole tile without
    the cull, with an odd tile or on the Pallas backend (its programs are whole tiles); set: itself."""
    c = RenderConfig()
    assert c.resolved_subtile() == 8
    assert dataclasses.replace(c, tile_cull=False).resolved_subtile() == 16
    assert RenderConfig(tile_size=15).resolved_subtile() == 15
    assert RenderConfig(backend="pallas").resolved_subtile() == 16
    assert RenderConfig(backend="pallas").resolved_backend() == "pallas"
    assert RenderConfig(subtile=4).resolved_subtile() == 4
    assert RenderConfig(subtile=16, tile_cull=False).resolved_subtile() == 16
