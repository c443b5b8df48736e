"""The interactive viewer (`cfgs_jax.app.viewer`) in headless Chromium."""

import numpy as np


def test_viewer_in_headless_chromium(fused_run):
    """`view`: the page loads in a real headless Chromium, the splats draw (screenshot not blank), two
    date selections look different, and clicking a date checkbox in the page changes the picture."""
    import io
    import shutil
    import time

    from PIL import Image
    from playwright.sync_api import sync_playwright

    from cfgs_jax.app.viewer import serve

    chromium = shutil.which("chromium")
    assert chromium, "Debian's chromium is needed (apt-get install chromium); the README test command installs it"
    viewer = serve(fused_run[0], port=0, block=False)
    flags = [
        "--no-sandbox",
        "--disable-background-networking",
        "--disable-component-update",
        "--use-angle=swiftshader",
        "--enable-unsafe-swiftshader",
    ]

    def shot(page):
        time.sleep(1.0)
        for _ in range(20):  # wait until two screenshots agree (the splats have arrived and been sorted)
            a = np.asarray(Image.open(io.BytesIO(page.screenshot())).convert("RGB"), np.float64)
            time.sleep(0.5)
            b = np.asarray(Image.open(io.BytesIO(page.screenshot())).convert("RGB"), np.float64)
            if np.abs(a - b).mean() < 0.05:
                return b
        return b

    try:
        with sync_playwright() as p:
            browser = p.chromium.launch(executable_path=chromium, headless=True, args=flags)
            page = browser.new_page(viewport={"width": 640, "height": 480})
            page.goto(f"http://127.0.0.1:{viewer.port}")
            page.get_by_text("d0", exact=True).first.wait_for(timeout=30_000)
            both = shot(page)
            viewer.splats.opacities = np.zeros((len(viewer.run.model), 1), np.float32)  # an empty scene, for reference
            empty = shot(page)
            viewer.update()
            page.get_by_text("d0", exact=True).first.click()  # untick d0 in the page
            only_d1 = shot(page)
            assert list(viewer.selection()) == [0.0, 1.0]
            page.get_by_text("d0", exact=True).first.click()
            page.get_by_text("d1", exact=True).first.click()
            only_d0 = shot(page)
            assert list(viewer.selection()) == [1.0, 0.0]
            browser.close()
    finally:
        viewer.stop()
    assert np.abs(both - empty).mean() > 2.0  # splats drew
    assert np.abs(only_d1 - both).mean() > 0.5 and np.abs(only_d0 - only_d1).mean() > 0.5
