"""A short fit with the learned kernel improves held-out views (Trainer, torch backend)."""
import torch

from splatk import backends
from splatk.metrics import psnr
from splatk.models.volumetric import SplatModel
from splatk.train.mcmc import MCMCConfig
from splatk.train.trainer import TrainConfig, Trainer
from tests.scenes import synthetic_scene


def test_short_learned_fit_raises_test_psnr():
    scene = synthetic_scene()
    bg = torch.tensor(scene.background)

    def test_psnr(model):
        with torch.no_grad():
            vals = [float(psnr(model.render(c, bg, sh_degree=1, backend=backends.get("torch")).image.clamp(0, 1),
                               c.image_float())) for c in scene.test]
        return sum(vals) / len(vals)

    torch.manual_seed(0)
    model = SplatModel.from_points(scene.points, scene.point_colors, kernel="learned", color="sh",
                                   kernel_options={"freeze_iters": 50}, color_options={"sh_degree": 1})
    before = test_psnr(model)
    cfg = TrainConfig(iters=150, budget=200, backend="torch", sh_degree_interval=50, seed=0,
                      mcmc=MCMCConfig(refine_start=50, refine_every=50))
    trainer = Trainer(scene, model, cfg)
    net0 = {k: v.clone() for k, v in model.kernel.state_dict().items()}
    trainer.run()
    after = test_psnr(trainer.model)
    # measured 19.6 -> 25.0 dB (torch 2.13 CPU); the networks trained after the freeze
    assert after > before + 3.0, (before, after)
    assert any(not torch.equal(net0[k], v) for k, v in trainer.model.kernel.state_dict().items())
    assert trainer.model.prims["z3d"].abs().sum() > 0
