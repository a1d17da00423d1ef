"""Dataset masks leave the training loss (no value, no gradient), and `--background random`
renders every step on a new colour with RGBA targets recomposited on it."""
from __future__ import annotations

import copy
import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from scenes import synthetic_scene  # noqa: E402

from splatk import backends
from splatk.models.volumetric import SplatModel
from splatk.stages.fit_config import fit_config_from_options
from splatk.train.losses import photometric_loss
from splatk.train.trainer import TrainConfig, Trainer

TORCH = backends.get("torch")


def left_half_mask(h: int, w: int) -> torch.Tensor:
    mask = torch.ones(h, w, dtype=torch.bool)
    mask[:, : w // 2] = False
    return mask


def test_masked_pixels_carry_no_gradient_and_do_not_change_the_loss():
    g = torch.Generator().manual_seed(0)
    image = torch.rand(20, 24, 3, generator=g, requires_grad=True)
    target = torch.rand(20, 24, 3, generator=g)
    mask = left_half_mask(20, 24)[..., None].float()
    loss = photometric_loss(image, target, TORCH, mask=mask)
    loss.backward()
    assert image.grad[:, :12].abs().max() == 0 and image.grad[:, 12:].abs().max() > 0
    other_image, other_target = image.detach().clone(), target.clone()
    other_image[:, :12] = torch.rand(20, 12, 3, generator=g)
    other_target[:, :12] = torch.rand(20, 12, 3, generator=g)
    assert torch.equal(photometric_loss(other_image, other_target, TORCH, mask=mask), loss.detach())
    # without a mask those pixels count
    assert not torch.equal(photometric_loss(other_image, other_target, TORCH), photometric_loss(image, target, TORCH))


def test_no_mask_is_the_loss_as_before():
    g = torch.Generator().manual_seed(1)
    image, target = torch.rand(16, 16, 3, generator=g), torch.rand(16, 16, 3, generator=g)
    expected = 0.8 * (image - target).abs().mean() + 0.2 * (1.0 - TORCH.ssim(image, target))
    assert torch.equal(photometric_loss(image, target, TORCH, mask=None), expected)


def _trainer(scene, **cfg) -> Trainer:
    torch.manual_seed(0)
    model = SplatModel.from_points(scene.points, scene.point_colors, color_options={"sh_degree": 1})
    return Trainer(scene, model, TrainConfig(iters=100, budget=200, backend="torch", **cfg))


def test_the_trainer_ignores_masked_pixels_of_its_targets():
    scene = synthetic_scene(num_views=8, size=32)
    for cam in scene.train:
        cam.mask = left_half_mask(cam.height, cam.width)
    scribbled = copy.deepcopy(scene)
    for cam in scribbled.train:
        cam.image = cam.image.clone()
        cam.image[:, :16] = torch.randint(0, 256, (cam.height, 16, 3), dtype=torch.uint8)
    a, b = _trainer(scene), _trainer(scribbled)
    for _ in range(3):
        sa, sb = a.train_step(), b.train_step()
        assert sa.loss == sb.loss and sa.psnr == sb.psnr
    for name in a.model.prims:
        assert torch.equal(a.model.prims[name], b.model.prims[name]), name
    # the mask is what made them equal
    for cam in scribbled.train:
        cam.mask = None
    assert _trainer(scribbled).train_step().loss != _trainer(scene).train_step().loss


def test_random_background_recomposites_rgba_targets():
    scene = synthetic_scene(num_views=8, size=32)
    alpha = torch.zeros(32, 32, dtype=torch.uint8)
    alpha[8:24, 8:24] = 255
    cam = scene.train[0]
    cam.alpha = alpha
    cam.image = cam.image.clone()
    cam.image[alpha == 0] = 255  # composited on the scene's white where transparent
    plain = _trainer(scene)
    background, target = plain._background_and_target(0)
    assert background is plain.background and target is plain.targets[0]
    tr = _trainer(scene, random_background=True)
    seen = []
    for _ in range(2):
        background, target = tr._background_and_target(0)
        seen.append(background)
        outside = alpha == 0
        # the scene's white background replaced by the drawn colour where the image is transparent
        assert torch.allclose(target[outside], (tr.targets[0] + background - tr.background)[outside], atol=1e-6)
        assert torch.allclose(target[outside], background.expand(int(outside.sum()), 3), atol=1 / 255)
        assert torch.equal(target[~outside], tr.targets[0][~outside])
    assert not torch.equal(seen[0], seen[1])
    # a view without alpha keeps its target, on a random background still
    background, target = tr._background_and_target(1)
    assert target is tr.targets[1] and not torch.equal(background, tr.background)
    info = tr.train_step()
    assert torch.isfinite(torch.tensor(info.loss))


def test_background_random_option():
    cfg, _ = fit_config_from_options({"background": "random"})
    assert cfg.train.random_background is True and cfg.background is None
    cfg, _ = fit_config_from_options({"background": "black"})
    assert cfg.train.random_background is False and cfg.background == [0.0, 0.0, 0.0]
