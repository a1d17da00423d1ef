"""Edge rows black in every image (video padding, letterboxing) leave the loss and the metrics:
the loader masks the band and the row a resize blends with it, at every downscale, names it in
the scene's warnings, and leaves scenes without such a band, and bands too wide to be a border,
as they were."""
from __future__ import annotations

import cv2
import numpy as np

from splatk.data import load_scene
from splatk.data.borders import BLACK, EdgeMeans, black_band
from splatk.metrics import psnr


def paint(root, bottom: int = 0, left: int = 0, blended: bool = True) -> None:
    """Rewrite a tiny scene's images: lit noise, ``bottom`` black rows and ``left`` black columns,
    and beside a black band a row at half brightness (what a resize leaves there)."""
    for path in sorted((root / "images").glob("*.png")):
        img = cv2.imread(str(path))
        img = np.maximum(img, 40)  # no lit row is near black by chance
        if bottom:
            if blended:
                img[-bottom - 1] //= 2
            img[-bottom:] = 0
        if left:
            img[:, :left] = 0
        cv2.imwrite(str(path), img)


def masked_rows(cam) -> list[int]:
    return (~cam.mask).all(1).nonzero().flatten().tolist() if cam.mask is not None else []


def test_black_bottom_rows_are_masked_with_their_blended_row(tiny_colmap):
    root = tiny_colmap(size=(40, 30))
    paint(root, bottom=2)
    scene = load_scene(root, test_every=0)
    for cam in scene.cameras:
        assert masked_rows(cam) == [27, 28, 29]  # two black rows and the blended one
        assert bool(cam.mask[:27].all())
    assert any("3 rows at the bottom" in w for w in scene.warnings), scene.warnings


def test_band_is_masked_at_the_downscaled_size(tiny_colmap):
    root = tiny_colmap(size=(40, 30))
    paint(root, bottom=1)
    cam = load_scene(root, test_every=0, downscale=4).cameras[0]
    # 30 rows to 8: output row 7 spans source rows 26.25-30, which hold the band (28-29); row 6
    # spans 22.5-26.25 and holds none of it
    assert (cam.height, masked_rows(cam)) == (8, [7])


def test_black_columns_are_masked(tiny_colmap):
    root = tiny_colmap(size=(40, 30))
    paint(root, left=1)
    cam = load_scene(root, test_every=0).cameras[0]
    keep = cam.mask
    assert not bool(keep[:, :2].any()) and bool(keep[:, 2:].all())


def test_scene_without_a_black_edge_has_no_mask(tiny_colmap):
    root = tiny_colmap(size=(40, 30))
    paint(root)
    scene = load_scene(root, test_every=0)
    assert all(c.mask is None for c in scene.cameras)
    assert not any("black" in w for w in scene.warnings)


def test_one_lit_image_keeps_the_row():
    """A row is a border only where every image is black there."""
    lit = np.full(4, 0.5)
    black = np.array([0.0, 0.0, 0.5, 0.5])
    means = [EdgeMeans(width=40, height=30, top=lit, bottom=black, left=lit, right=lit),
             EdgeMeans(width=40, height=30, top=lit, bottom=np.array([0.0, 2 * BLACK, 0.5, 0.5]), left=lit, right=lit)]
    assert black_band(means) == {"top": 0, "bottom": 2, "left": 0, "right": 0}
    means[1] = EdgeMeans(width=40, height=30, top=lit, bottom=lit, left=lit, right=lit)
    assert black_band(means)["bottom"] == 0


def test_band_wider_than_an_eighth_is_the_scene():
    """A dark room, not a border: a run of black rows past 1/8 of the image stays in."""
    dark = np.zeros(6)  # every row looked at is black: a band of 7 with the blended row, past 30 / 8
    lit = np.full(6, 0.5)
    assert black_band([EdgeMeans(width=40, height=30, top=dark, bottom=lit, left=lit, right=lit)])["top"] == 0


def test_metrics_leave_the_band_out(tiny_colmap):
    """A render wrong only in the black band scores as a perfect one; without the mask it would not."""
    root = tiny_colmap(size=(40, 30))
    paint(root, bottom=2)
    cam = load_scene(root, test_every=0).cameras[0]
    target = cam.image_float()
    wrong_band_only = target.clone()
    wrong_band_only[27:] = 1.0
    assert float(psnr(wrong_band_only, target)) < 15
    assert float(psnr(wrong_band_only, target, mask=cam.mask_float())) > 60
