"""A process's peak resident memory per stage (cfgs_jax.resources)."""

import sys

import pytest


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="/proc/self/status is Linux-only")
def test_peak_rss_counts_from_the_last_reset():
    """A 300 MB buffer touched and freed raises the peak by ≥ 300 MB; after a reset the peak is back
    near the current RSS (the window of the next stage starts clean)."""
    import numpy as np

    from cfgs_jax import resources

    assert resources.reset_peak_rss()
    base = resources.peak_rss_bytes()
    block = np.ones(300_000_000 // 8)  # written: resident
    assert float(block[-1]) == 1.0
    del block
    assert resources.peak_rss_bytes() >= base + 290e6
    resources.reset_peak_rss()
    assert resources.peak_rss_bytes() < base + 100e6
