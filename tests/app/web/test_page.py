"""The static web page (`export --format web`, `cfgs_jax.app.web`) in headless Chromium."""

import numpy as np


def test_exported_web_page_in_headless_chromium_draws_each_date_like_our_renderer(fused_run, tmp_path):
    """`export --format web`: the page opens from disk in a real headless Chromium; at a test camera
    each date alone and both dates (blend) and the highlight, drawn by the vendored renderer, match
    our own render of that camera (PSNR ≥ 30 dB); clicking a date and the highlight in the page
    switches to the selection clicked (drawn like our render of it); served over HTTP it fetches the .spz files instead of their scripts."""
    import functools
    import http.server
    import io
    import json
    import shutil
    import threading
    import time

    from PIL import Image
    from playwright.sync_api import sync_playwright

    from cfgs_jax import viz
    from cfgs_jax.app.pipeline import main
    from cfgs_jax.app.render_run import SelectionStyle, open_run

    run_dir = fused_run[0]
    out = tmp_path / "page"
    assert main(["export", "--run", str(run_dir), "--format", "web", "--out", str(out), "--no-progress"]) == 0
    manifest = json.loads((out / "manifest.json").read_text())
    # an earlier page is replaced; a folder holding anything else is refused, untouched
    assert main(["export", "--run", str(run_dir), "--format", "web", "--out", str(out), "--no-progress"]) == 0
    (tmp_path / "other").mkdir()
    (tmp_path / "other" / "keep.txt").write_text("x")
    assert main(["export", "--run", str(run_dir), "--format", "web", "--out", str(tmp_path / "other")]) == 2
    assert [p.name for p in (tmp_path / "other").iterdir()] == ["keep.txt"]
    assert sorted(manifest["selections"]) == sorted(
        f"{t}_{m}" for t in ("11", "10", "01") for m in ("blend", "max", "highlight")
    )
    assert (out / "licences" / "LICENSE-spark.txt").is_file() and (out / "splat-viewer.js").stat().st_size > 1e6
    run = open_run(run_dir)
    name, cam = run.test_cameras()[0]
    assert manifest["cameras"][0]["name"] == name
    chromium = shutil.which("chromium")
    assert chromium, "Debian's chromium is needed (apt-get install chromium); the README test command installs it"
    flags = [
        "--no-sandbox",
        "--use-angle=swiftshader",
        "--enable-unsafe-swiftshader",
        "--disable-background-networking",
    ]

    def ready(page, key):
        page.wait_for_function(
            f"document.body.dataset.key === '{key}' && document.body.dataset.state === 'ready'", timeout=60_000
        )

    def shot(page):
        time.sleep(0.5)
        for _ in range(20):  # until two screenshots agree (Spark sorts in a worker)
            a = np.asarray(Image.open(io.BytesIO(page.locator("#view").screenshot())).convert("RGB"), np.float64)
            time.sleep(0.5)
            b = np.asarray(Image.open(io.BytesIO(page.locator("#view").screenshot())).convert("RGB"), np.float64)
            if np.abs(a - b).mean() < 0.05:
                break
        return b / 255

    psnr = {}
    handler = functools.partial(http.server.SimpleHTTPRequestHandler, directory=str(out))
    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), handler)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    try:
        with sync_playwright() as p:
            browser = p.chromium.launch(executable_path=chromium, headless=True, args=flags)
            page = browser.new_page(viewport={"width": 800, "height": 600})
            errors = []
            page.on("pageerror", lambda e: errors.append(str(e)))
            page.goto((out / "index.html").as_uri())
            ready(page, "11_blend")
            page.evaluate("cfgs.view(0)")
            for key in ("11_blend", "10_blend", "01_blend", "11_highlight"):
                page.evaluate(f"cfgs.show('{key}')")
                ready(page, key)
                t, mode = key.split("_")
                want = viz.render_selection(run.model, cam, [float(c) for c in t], **SelectionStyle(mode=mode).kwargs())
                want = np.clip(np.asarray(want.image, np.float64), 0, 1)
                got = shot(page)
                assert got.shape == want.shape
                psnr[key] = 10 * np.log10(1 / np.mean((got - want) ** 2))
            # the toggles: untick d0 (→ d1 alone), then the highlight
            page.evaluate("cfgs.show('11_blend')")
            ready(page, "11_blend")
            page.get_by_text("d0", exact=True).first.click()
            ready(page, "01_blend")
            page.locator("#highlight").click()
            ready(page, "01_highlight")
            highlighted = shot(page)
            want = viz.render_selection(run.model, cam, [0.0, 1.0], **SelectionStyle(mode="highlight").kwargs())
            psnr["01_highlight (clicked)"] = 10 * np.log10(1 / np.mean((highlighted - np.clip(want.image, 0, 1)) ** 2))
            assert not errors
            # over HTTP the page fetches the .spz files
            fetched = []
            page.on("request", lambda r: fetched.append(r.url))
            page.goto(f"http://127.0.0.1:{server.server_address[1]}/index.html")
            ready(page, "11_blend")
            assert any(u.endswith("splats/11_blend.spz") for u in fetched)
            assert not any(u.endswith(".spz.js") for u in fetched)
            browser.close()
    finally:
        server.shutdown()
    print("web page PSNR against our render:", {k: round(v, 2) for k, v in psnr.items()})
    assert min(psnr.values()) >= 30.0, psnr
