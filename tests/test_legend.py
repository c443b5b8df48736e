"""The legend strip under rendered views (cfgs_jax.legend): each date's swatch in its highlight colour when
selected, an empty grey outline when not, on the strip's dark ground."""

import numpy as np

from cfgs_jax import viz
from cfgs_jax.legend import legend_strip

GROUND = 24 / 255


def _swatches(strip: np.ndarray) -> list[tuple[int, int]]:
    """The x ranges of the swatches: 8-pixel boxes whose outline covers rows 4 and 11 (found by scanning
    row 4, where only swatch outlines are drawn: the names' glyphs start lower)."""
    row = np.abs(strip[4] - GROUND).max(-1) > 1e-6
    edges = np.flatnonzero(np.diff(np.concatenate([[0], row.astype(int), [0]])))
    return [(a, b) for a, b in zip(edges[::2], edges[1::2]) if b - a == 9]


def test_selected_dates_show_their_highlight_colour_and_unselected_an_empty_grey_box():
    names = ["d0", "flood", "d2"]
    strip = legend_strip(names, [1, 0, 1], 240, highlight=True)
    assert strip.shape == (16, 240, 3) and strip.dtype == np.float32
    assert strip.min() >= 0 and strip.max() <= 1
    boxes = _swatches(strip)
    assert len(boxes) == 3
    colours = np.round(viz.date_colours(3, viz.DEFAULT_STOPS) * 255) / 255
    for k, (a, b) in enumerate(boxes):
        inside = strip[6:10, a + 2 : b - 2]
        if k == 1:  # unselected: a 0.45 grey outline around the dark ground
            np.testing.assert_allclose(strip[4, a:b], np.round(0.45 * 255) / 255, atol=1e-6)
            np.testing.assert_allclose(inside, GROUND, atol=1e-6)
        else:
            np.testing.assert_allclose(inside, np.broadcast_to(colours[k], inside.shape), atol=1e-6)


def test_a_plain_blend_draws_every_selected_date_white():
    strip = legend_strip(["a", "b"], [1, 1], 120, highlight=False)
    boxes = _swatches(strip)
    assert len(boxes) == 2
    for a, b in boxes:
        np.testing.assert_allclose(strip[6:10, a + 2 : b - 2], 1.0, atol=1e-6)
