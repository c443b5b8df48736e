"""A static web page of a fused run (``export --format web``): toggles per date, blend / max and the
change highlight, rendered in the browser by a vendored splatting library (``web/vendor``)."""

from cfgs_jax.app.web.page import page_selections, write_web_page

__all__ = ["page_selections", "write_web_page"]
