"""The application layer: what a user runs, above the library.

- :mod:`cfgs_jax.app.cli`: the command line's grammar; :mod:`cfgs_jax.app.pipeline`: what each command does
  (run as ``python -m cfgs_jax.pipeline`` or ``cfgs-jax``);
- :mod:`cfgs_jax.app.render_run`: a fused run opened for rendering any time selection, with or without the
  change highlight; :mod:`cfgs_jax.app.viewer`: the interactive viser viewer over it;
- :mod:`cfgs_jax.app.web`: the static web page export; :mod:`cfgs_jax.app.demo`: the embedded default job.

Nothing in the library below imports from here.
"""
