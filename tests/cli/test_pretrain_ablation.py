"""`splatk pretrain` shapes the networks as the paper's ablations do (Tab. 3/4: Phi_proj's inputs,
latent sizes, widths), and `splatk fit --kernel-weights` takes that shape from the file."""
from __future__ import annotations

import torch
import yaml
from click.testing import CliRunner

from splatk.data.synthetic import make_demo_scene
from splatk_cli.main import cli


def test_pretrained_shape_is_used_by_fit(tmp_path):
    weights = tmp_path / "w.pt"
    res = CliRunner().invoke(cli, ["pretrain", "--target", "linear", "--out", str(weights), "--steps", "20",
                                   "--proj-inputs", "z,s,R", "--latent-dim", "2", "--proj-width", "16",
                                   "--dec-width", "8", "-q"])
    assert res.exit_code == 0, res.output
    state = torch.load(weights, weights_only=True)
    assert state["options"]["latent_dim"] == 2 and state["options"]["proj_inputs"] == "z,s,R"
    assert state["state_dict"]["dec.0.weight"].shape[0] == 8
    scene = make_demo_scene(tmp_path / "scene", num_views=6, size=24)
    run = tmp_path / "run"
    res = CliRunner().invoke(cli, ["fit", str(scene), "--out", str(run), "--kernel", "learned", "--kernel-weights",
                                   str(weights), "--iters", "10", "--budget", "50", "--backend", "torch", "-q"])
    assert res.exit_code == 0, res.output
    opts = yaml.safe_load((run / "config.yaml").read_text())["settings"]["kernel_options"]
    assert (opts["latent_dim"], opts["proj_inputs"], opts["proj_width"], opts["dec_width"]) == (2, "z,s,R", 16, 8)
    assert opts["weights"] == str(weights.absolute())
    model = torch.load(run / "model.pt", weights_only=True)
    assert model["prims"]["z3d"].shape[1] == 2


def test_shape_options_are_volumetric_only(tmp_path):
    res = CliRunner().invoke(cli, ["pretrain", "--kind", "planar", "--out", str(tmp_path / "p.pt"),
                                   "--latent-dim", "2", "-q"])
    assert res.exit_code == 2 and "volumetric" in res.output
