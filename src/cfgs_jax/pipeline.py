"""``python -m cfgs_jax.pipeline <command> ...``: the command line under the name users run.

The commands live in the application layer, :mod:`cfgs_jax.app` (what each does: :mod:`cfgs_jax.app.pipeline`;
the grammar: :mod:`cfgs_jax.app.cli`); this module only gives them their entry point.
"""

import sys

from cfgs_jax.app.pipeline import main

__all__ = ["main"]

if __name__ == "__main__":
    sys.exit(main())
