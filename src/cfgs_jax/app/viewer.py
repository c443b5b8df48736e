"""Browser viewer of a fused run (CLI ``view``), built on viser's Gaussian-splat scene node.

Controls: a checkbox per date (the time selection t), the mode (blend / max / highlight), a grey-base
toggle, σ of the persistence filter, the contrast sigmoid (on/off, k, b) and the highlight gradient.
Every change recomputes the per-Gaussian colours and opacities with one jitted function of
``cfgs_jax.viz`` and updates the splats in place; for a model with SH (view-dependent colour) a camera
move does too, the colours evaluated from the moved camera's position (``viz.at_view``; with several
browsers open, the last one moved). The server listens on 127.0.0.1 only.
"""

from __future__ import annotations

import functools
import threading
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from cfgs_jax import viz
from cfgs_jax.app.render_run import FusedRun, SelectionStyle, open_run
from cfgs_jax.errors import InputError
from cfgs_jax.model import covariances, opacities
from cfgs_jax.orbit import orbit_geometry

#: Gradient choices offered by the viewer (linear RGB stops; None = the full-RGB filter, no remap).
GRADIENTS: dict[str, tuple | None] = {
    "blue-red (authors')": viz.DEFAULT_STOPS,
    "teal-yellow": ((0.0, 0.35, 0.45), (0.2, 0.6, 0.3), (1.0, 0.8, 0.0)),
    "two colours (blue-orange)": ((0.1, 0.2, 1.0), (1.0, 0.45, 0.0)),
    "RGB (no remap)": None,
}
MODES = ("highlight", "blend", "max")


@functools.partial(jax.jit, static_argnames=("mode", "base", "stops", "use_contrast"))
def splat_terms(model, t, centre, sigma, k, b, *, mode: str, base: str, stops, use_contrast: bool):
    """(rgb [N,3] in [0,1], opacity [N]) of the viewer's current settings (Eq. 4 / Eq. 5) seen from the
    camera position ``centre``."""
    style = SelectionStyle(mode=mode, base=base, sigma=sigma, contrast=(k, b) if use_contrast else None, stops=stops)
    colours, mult = style.terms(viz.at_view(model, centre), t)
    return jnp.clip(colours, 0.0, 1.0), opacities(model.gaussians) * mult


class Viewer:
    """A running viser server showing one fused run; ``settings`` holds the current controls."""

    def __init__(self, run: FusedRun, *, port: int = 8080):
        try:
            import viser
        except ImportError:
            raise InputError(
                "viser (the viewer extra) is not installed", field="view", fix='pip install "cfgs-jax[viewer]"'
            ) from None
        self.run = run
        self.server = viser.ViserServer(host="127.0.0.1", port=port, verbose=False)
        self.port = self.server.get_port()
        self._lock = threading.Lock()
        model = run.model
        g = model.gaussians
        target, up, e1, e2, radius, height = orbit_geometry(run.all_cameras())
        self._eye = target + height * up + radius * e1
        self._centre = np.asarray(self._eye, np.float32)  # where the colours are seen from
        self._target, self._up = target, up
        self.server.scene.set_up_direction(tuple(float(v) for v in up))
        gui = self.server.gui
        with gui.add_folder("Dates"):
            self.date_boxes = [gui.add_checkbox(name, initial_value=True) for name in run.names]
        self.mode = gui.add_dropdown("Mode", MODES, initial_value="highlight")
        self.grey = gui.add_checkbox("Grey base", initial_value=True)
        self.sigma = gui.add_slider("σ (persistence)", min=0.02, max=0.6, step=0.01, initial_value=viz.DEFAULT_SIGMA)
        self.use_contrast = gui.add_checkbox("Contrast sigmoid", initial_value=False)
        self.k = gui.add_slider("contrast k", min=0.5, max=12.0, step=0.5, initial_value=4.0)
        self.b = gui.add_slider("contrast b", min=0.05, max=0.95, step=0.05, initial_value=0.5)
        self.gradient = gui.add_dropdown("Gradient", tuple(GRADIENTS), initial_value=next(iter(GRADIENTS)))
        self.status = gui.add_markdown("")
        rgb, alpha = self._terms()
        self.splats = self.server.scene.add_gaussian_splats(
            "/model",
            centers=np.asarray(g.means, np.float32),
            covariances=np.asarray(covariances(g), np.float32),
            rgbs=rgb,
            opacities=alpha[:, None],
        )
        for control in (
            *self.date_boxes,
            self.mode,
            self.grey,
            self.sigma,
            self.use_contrast,
            self.k,
            self.b,
            self.gradient,
        ):
            control.on_update(lambda _event: self.update())

        @self.server.on_client_connect
        def _(client):
            client.camera.up_direction = tuple(float(v) for v in self._up)
            client.camera.position = tuple(float(v) for v in self._eye)
            client.camera.look_at = tuple(float(v) for v in self._target)
            if g.sh_rest is not None:
                client.camera.on_update(self.moved)

    def selection(self) -> np.ndarray:
        return np.asarray([float(box.value) for box in self.date_boxes])

    def _terms(self) -> tuple[np.ndarray, np.ndarray]:
        t = self.selection()
        n = len(self.run.model)
        if not t.any():
            self.status.content = "*No date selected: nothing to show.*"
            return np.zeros((n, 3), np.float32), np.zeros(n, np.float32)
        self.status.content = "Selection: " + ", ".join(nm for nm, s in zip(self.run.names, t) if s)
        rgb, alpha = splat_terms(
            self.run.model,
            jnp.asarray(t, jnp.float32),
            jnp.asarray(self._centre),
            float(self.sigma.value),
            float(self.k.value),
            float(self.b.value),
            mode=self.mode.value,
            base="grey" if self.grey.value else "colour",
            stops=GRADIENTS[self.gradient.value],
            use_contrast=bool(self.use_contrast.value),
        )
        return np.asarray(rgb, np.float32), np.asarray(alpha, np.float32)

    def update(self) -> None:
        """Recompute colours/opacities from the controls and push them to the splats."""
        with self._lock:
            rgb, alpha = self._terms()
            self.splats.rgbs = rgb
            self.splats.opacities = alpha[:, None]

    def moved(self, camera) -> None:
        """A browser's camera moved: the view-dependent colours are seen from its new position."""
        self._centre = np.asarray(camera.position, np.float32)
        self.update()

    def stop(self) -> None:
        self.server.stop()


def serve(run_dir: str | Path, *, port: int = 8080, block: bool = True) -> Viewer:
    """Open ``RUN`` and serve the viewer on http://127.0.0.1:<port>; ``block`` waits until Ctrl-C."""
    viewer = Viewer(open_run(run_dir), port=port)
    if block:
        try:
            while True:
                time.sleep(3600)
        except KeyboardInterrupt:
            viewer.stop()
    return viewer
