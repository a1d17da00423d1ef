"""`--batch-views B`: each step renders B train views and averages their losses, with the
learning rates raised by sqrt(B); B = 1 is the trainer as it always was."""
from __future__ import annotations

import math
import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from scenes import synthetic_scene  # noqa: E402

from splatk.models.volumetric import SplatModel
from splatk.train.losses import photometric_loss, regularisers
from splatk.train.trainer import TrainConfig, Trainer


def trainer(batch_views: int) -> Trainer:
    scene = synthetic_scene(num_views=8)
    torch.manual_seed(0)
    model = SplatModel.from_points(scene.points, scene.point_colors, color_options={"sh_degree": 1})
    return Trainer(scene, model, TrainConfig(iters=20, budget=100, backend="torch", batch_views=batch_views))


def test_the_step_loss_is_the_mean_over_the_batch():
    tr = trainer(2)
    tr.view_queue = [5, 3]  # popped from the end: views 3 then 5
    with torch.no_grad():
        per_view = [photometric_loss(tr.model.render(tr.scene.train[v], tr.background, sh_degree=0,
                                                     backend=tr.backend).image, tr.targets[v], tr.backend, 0.2)
                    for v in (3, 5)]
        expected = float(sum(per_view) / 2 + regularisers(tr.model, 0.01, 0.01))
    info = tr.train_step()
    assert math.isclose(info.loss, expected, rel_tol=1e-6)
    assert tr.view_queue == []  # both views used by the one step


def test_learning_rates_rise_by_the_square_root_of_the_batch():
    one, two = trainer(1), trainer(2)
    one.train_step(), two.train_step()
    for name in ("log_scales", "sh0", "opacity_logits"):
        lr1 = one.opt._group(name)["lr"]
        assert math.isclose(two.opt._group(name)["lr"], lr1 * math.sqrt(2), rel_tol=1e-9), name


def test_batches_train():
    tr = trainer(4)
    first = tr.train_step().loss
    for _ in range(19):
        last = tr.train_step()
    assert last.it == 20 and last.loss < first
