"""`splatk view` in a real headless Chromium: the page opens, a frame arrives, and the picture on
the page is `eval`'s render of the same camera; the panel shows the frame time and jumps to a
picked camera; frames shrink while the camera moves. Needs the `playwright` package and Debian's
`chromium` package (/usr/bin/chromium, or the browser that SPLATK_CHROMIUM names);
`bash .ci/install_test_assets.sh` installs it when run as root."""
from __future__ import annotations

import io
import os
import re
import shutil
import time

import numpy as np
import pytest
import torch

from splatk import backends
from splatk.data import load_scene
from splatk.data.synthetic import make_demo_scene
from splatk.models.io import load_model
from splatk.stages.fit import FitConfig, run_fit
from splatk.train.trainer import TrainConfig
from tests.viewer_process import start_viewer, stop_viewer

pytest.importorskip("viser")
sync_api = pytest.importorskip("playwright.sync_api", reason="needs playwright: pip install -e \".[dev]\"")
CHROMIUM = os.environ.get("SPLATK_CHROMIUM") or shutil.which("chromium") or "/usr/bin/chromium"
if not os.path.exists(CHROMIUM):
    pytest.skip("needs Chromium: apt-get install -y chromium (as root: bash .ci/install_test_assets.sh)",
                allow_module_level=True)

# Headless without a GPU: WebGL through SwiftShader; the background-networking flags keep the
# browser from calling home on a closed network.
CHROMIUM_ARGS = ["--headless", "--no-sandbox", "--disable-gpu", "--use-gl=angle", "--use-angle=swiftshader",
                 "--disable-quic", "--no-first-run", "--disable-background-networking",
                 "--disable-component-update", "--disable-sync"]
SIZE = 48          # the scene's images are SIZE x SIZE
WINDOW = 8 * SIZE  # the browser window: each image pixel is an 8 x 8 block on the page
# viser draws an orientation gizmo in the canvas's bottom-left corner (about 60 page pixels)
GIZMO = (slice(SIZE - 9, SIZE), slice(0, 9))


@pytest.fixture(scope="module")
def learned_run(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("view_browser")
    scene = make_demo_scene(tmp / "scene", num_views=16, size=SIZE)
    cfg = FitConfig(kernel="learned", kernel_options={"k": 2}, sh_degree=1, backend="torch", threads=1,
                    train=TrainConfig(iters=60, budget=400, init="random", backend="torch"))
    return run_fit(scene, tmp / "run", cfg).path


@pytest.fixture
def viewer(learned_run, request):
    """`splatk view` serving the run at its test camera test/r_8.png (more options: the test's
    indirect parameter); the server is always stopped, and a test fails if it died on the way."""
    viewer = start_viewer(learned_run, "--backend", "torch", "--camera", "test/r_8.png",
                          *getattr(request, "param", ()))
    try:
        yield viewer.url
    finally:
        died = viewer.proc.poll()
        code, err = stop_viewer(viewer)
    assert died is None, f"splatk view exited with {died} during the test: {err}"
    assert code == 0, f"splatk view did not stop cleanly on Ctrl-C ({code}): {err}"


@pytest.fixture
def page(viewer):
    with sync_api.sync_playwright() as p:
        browser = p.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS, timeout=60_000)
        try:
            page = browser.new_page(viewport={"width": WINDOW, "height": WINDOW})
            page.set_default_timeout(60_000)
            # a fixed pixel ratio: viser's client otherwise lowers it when the browser draws slowly
            # (SwiftShader on a busy CPU), and it tells the server the new canvas size only when the
            # camera next moves, so a frame drawn at rest may stay the old size
            page.goto(viewer + "?fixedDpr=1")
            yield page
        finally:
            browser.close()


def _eval_render(run, name: str) -> np.ndarray:
    """[SIZE, SIZE, 3] float: the test or train view ``name`` as `splatk eval` renders it."""
    model, meta = load_model(run / "model.pt")
    scene = load_scene(meta["scene"], test_every=meta["test_every"], load_images=False)
    (cam,) = [c for c in scene.test + scene.train if c.name == name]
    with torch.no_grad():
        img = model.render(cam, torch.tensor(scene.background), backend=backends.get("torch", "cpu")).image
    return (img.clamp(0, 1).numpy() * 255 + 0.5).astype(np.uint8).astype(float)


def _shown_image(page) -> np.ndarray:
    """[SIZE, SIZE, 3] float: the canvas with the panel and notices hidden, each 8 x 8 block
    averaged back to one pixel."""
    from PIL import Image

    page.add_style_tag(content="body * { visibility: hidden !important } canvas { visibility: visible !important }")
    box = page.locator("canvas").last.bounding_box()
    assert (round(box["width"]), round(box["height"])) == (WINDOW, WINDOW), box
    png = page.screenshot(clip=box, animations="disabled")
    shot = np.asarray(Image.open(io.BytesIO(png)).convert("RGB"), dtype=float)
    return shot.reshape(SIZE, WINDOW // SIZE, SIZE, WINDOW // SIZE, 3).mean(axis=(1, 3))


def _psnr(a: np.ndarray, b: np.ndarray) -> float:
    keep = np.ones(a.shape[:2], bool)
    keep[GIZMO] = False
    return 10 * np.log10(255.0 ** 2 / float(((a - b) ** 2)[keep].mean()))


def _frame_size(page) -> tuple[int, int]:
    """The size of the last frame, as the panel reports it."""
    text = page.get_by_text(re.compile(r"Frame: \d+ ms, \d+×\d+")).inner_text()
    width, height = re.search(r"(\d+)×(\d+)", text).groups()
    return int(width), int(height)


def _canvas_size(page) -> tuple[int, int]:
    """The drawing buffer of viser's WebGL canvas: the client reports it as the camera's image
    size (the window's size at the page's fixed pixel ratio of 1)."""
    sizes = page.evaluate("() => [...document.querySelectorAll('canvas')].map(c => [c.width, c.height])")
    return tuple(max(sizes, key=lambda wh: wh[0] * wh[1]))


def _wait_for_full_frame(page, timeout: float = 60.0) -> tuple[int, int]:
    """Until the panel reports a frame as large as the canvas (the frame drawn once the camera
    rests); returns that size."""
    deadline = time.time() + timeout
    while True:
        frame, canvas = _frame_size(page), _canvas_size(page)
        if frame == canvas:
            return frame
        assert time.time() < deadline, f"no frame of the canvas's size {canvas} within {timeout:.0f} s: last {frame}"
        time.sleep(0.2)


def _shows(page, ref: np.ndarray, timeout: float = 30.0) -> tuple[float, np.ndarray]:
    """The page's picture and its PSNR against ``ref`` once it matches (above 25 dB), or the last
    ones seen after ``timeout`` seconds (the browser may paint the frame a moment after it arrives)."""
    deadline = time.time() + timeout
    while True:
        shown = _shown_image(page)
        psnr = _psnr(shown, ref)
        if psnr > 25 or time.time() > deadline:
            return psnr, shown
        time.sleep(0.5)


def test_the_page_shows_evals_render_of_the_camera(learned_run, page):
    _wait_for_full_frame(page)
    ref, other = _eval_render(learned_run, "test/r_8.png"), _eval_render(learned_run, "test/r_0.png")
    assert ref.std() > 10  # the model, not an empty background
    psnr, shown = _shows(page, ref)
    # JPEG and the browser's resampling cost a little; another camera or a blank frame costs far more
    assert psnr > 25, f"the viewer shows something else than eval's render (PSNR {psnr:.1f} dB)"
    assert _psnr(shown, other) < psnr - 5
    assert _psnr(shown, np.full_like(ref, 255.0)) < psnr - 5


def test_the_camera_list_jumps_to_the_picked_camera(learned_run, page):
    _wait_for_full_frame(page)
    field = page.get_by_role("combobox", name="Camera", exact=True)
    field.click()
    field.fill("test/r_0")
    page.get_by_role("option", name="test/r_0.png").click()
    ref = _eval_render(learned_run, "test/r_0.png")
    psnr, _ = _shows(page, ref, timeout=60)
    assert psnr > 25, f"after picking test/r_0.png the viewer does not show it (PSNR {psnr:.1f} dB)"


# no frame is drawn in a millisecond, so every frame while the camera moves is smaller than the last
@pytest.mark.parametrize("viewer", [("--fps", "1000")], indirect=True)
def test_frames_shrink_while_the_camera_moves_and_sharpen_at_rest(page):
    full = _wait_for_full_frame(page)
    assert full == (WINDOW, WINDOW)  # the page's pixel ratio is 1
    y = 0.8 * WINDOW  # below the panel
    page.mouse.move(0.2 * WINDOW, y)
    page.mouse.down()
    sizes = set()
    for i in range(40):  # an orbit drag of about two seconds
        page.mouse.move(0.2 * WINDOW + 5 * i, y)
        time.sleep(0.05)
        sizes.add(_frame_size(page))
    page.mouse.up()
    assert any(width < full[0] for width, _ in sizes), f"frames while moving: {sorted(sizes)}"
    assert all(width / height == pytest.approx(1.0, abs=0.05) for width, height in sizes)  # the window's aspect
    assert _wait_for_full_frame(page) == full  # once the camera rests
