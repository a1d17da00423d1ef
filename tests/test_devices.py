"""`--device`: the engine's torch paths give the CPU's images and gradients on a GPU, and every
command that takes `--device` trains / renders there end to end.

CI has no GPU, so the CUDA tests skip there; they ran on an H100 (docs/results.md, "GPU
check"). The checks of a bad `--device` run everywhere.
"""
from __future__ import annotations

import copy
import json
import sys
from pathlib import Path

import pytest
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from scenes import orbit_cameras, random_model, synthetic_scene  # noqa: E402

from splatk import backends
from splatk.data.synthetic import make_demo_scene
from splatk.device import resolve_device
from splatk.errors import InputError
from splatk.models.planar import PlanarModel
from splatk.stages.autobudget import AutoBudgetConfig
from splatk.stages.evaluate import run_eval
from splatk.stages.fit import FitConfig, run_fit
from splatk.stages.run_length import scale_schedules_to_run
from splatk.image.fit import ImageFitConfig, fit_image
from splatk.train.mcmc import MCMCConfig
from splatk.train.trainer import TrainConfig

cuda = pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device here")


def test_unknown_or_missing_device_is_an_input_error():
    with pytest.raises(InputError, match="--device 'gpu0': not a torch device"):
        resolve_device("gpu0")
    if not torch.cuda.is_available():
        with pytest.raises(InputError, match="--device 'cuda': not usable here"):
            resolve_device("cuda")
    with pytest.raises(InputError, match="native.*CPU only"):
        resolve_device("meta", backend="cpu")
    assert resolve_device("cpu", backend="cpu") == torch.device("cpu")


def test_fit_refuses_a_missing_device_before_any_work(tmp_path):
    scene = make_demo_scene(tmp_path / "demo", num_views=4, size=16)
    bad = "cuda:99" if torch.cuda.is_available() else "cuda"
    with pytest.raises(InputError, match="not usable here"):
        run_fit(scene, tmp_path / "run", FitConfig(device=bad, train=TrainConfig(device=bad)))
    assert not (tmp_path / "run" / "checkpoints").exists()


def _render_and_grads(model, cam, dev: str):
    """Image and every parameter's gradient of a fixed weighted sum of it, on ``dev``."""
    m = copy.deepcopy(model).to(dev)
    bg = torch.tensor([1.0, 1.0, 1.0], device=dev)
    img = m.render(cam, bg, sh_degree=1, backend=backends.get("torch")).image
    w = torch.linspace(-1.0, 1.0, img.numel(), device=dev).reshape(img.shape)
    (img * w).sum().backward()
    grads = {n: p.grad.detach().cpu() for n, p in m.named_parameters() if p.grad is not None}
    return img.detach().cpu(), grads


def _assert_same_render(model, cam):
    img_cpu, g_cpu = _render_and_grads(model, cam, "cpu")
    img_gpu, g_gpu = _render_and_grads(model, cam, "cuda")
    torch.testing.assert_close(img_gpu, img_cpu, atol=2e-5, rtol=0)
    assert g_cpu.keys() == g_gpu.keys() and g_cpu
    for name, ref in g_cpu.items():
        # float32 with another summation order (atomics on the GPU): relative to the largest
        torch.testing.assert_close(g_gpu[name], ref, atol=2e-4 * float(ref.abs().max()) + 1e-7, rtol=2e-3,
                                   msg=lambda m: f"{name}: {m}")


@cuda
@pytest.mark.parametrize("kernel", ["gaussian", "beta", "student_t", "learned"])
def test_volumetric_render_and_gradients_match_the_cpu(kernel):
    torch.manual_seed(0)
    _assert_same_render(random_model(60, seed=1, kernel=kernel), orbit_cameras(3)[1])


@cuda
@pytest.mark.parametrize("kernel", ["gaussian", "learned"])
def test_planar_render_and_gradients_match_the_cpu(kernel):
    scene = synthetic_scene(num_views=4, size=24)
    torch.manual_seed(1)
    model = PlanarModel.from_points(scene.points, scene.point_colors, kernel=kernel,
                                    color_options={"sh_degree": 1})
    _assert_same_render(model, scene.train[0])


@cuda
@pytest.mark.parametrize("primitive, kernel", [("volumetric", "gaussian"), ("volumetric", "learned"),
                                               ("planar", "gaussian")])
def test_fit_eval_and_resume_on_cuda(primitive, kernel, tmp_path):
    """`fit --device cuda` learns the demo scene, stops and resumes there, and `eval` measures the
    model the same on the GPU as on the CPU."""
    scene = make_demo_scene(tmp_path / "demo", num_views=12, size=48)
    train = TrainConfig(iters=300, budget=1000, device="cuda")
    cfg = FitConfig(primitive=primitive, kernel=kernel, sh_degree=1, device="cuda", backend="auto", train=train)
    scale_schedules_to_run(cfg)  # as `splatk fit` does (CPU, gaussian: 10.0 -> 14.3 dB in 300 steps)
    run = tmp_path / "run"
    calls = {"n": 0}

    def ctrl_c():  # interrupt mid-run, as Ctrl-C does
        calls["n"] += 1
        if calls["n"] == 150:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        run_fit(scene, run, cfg, should_stop=ctrl_c)
    assert (run / "checkpoints" / "last.pt").is_file() and not (run / "model.pt").exists()
    run_fit(scene, run, cfg, resume=True)
    summary = json.loads((run / "fit.json").read_text())
    assert summary["iterations"] == 300
    gpu = run_eval(run, ("psnr", "ssim"), device="cuda")
    cpu = run_eval(run, ("psnr", "ssim"), device="cpu", backend="torch")
    assert gpu["device"].startswith("cuda") and cpu["device"] == "cpu"
    assert gpu["backend"] == backends.resolve_backend("auto", "cuda") == "cuda"  # Triton's, on a GPU
    assert gpu["mean"]["psnr"] > summary["initial_psnr"] + 3.0, (summary["initial_psnr"], gpu["mean"])
    assert abs(gpu["mean"]["psnr"] - cpu["mean"]["psnr"]) < 1e-2
    assert abs(gpu["mean"]["ssim"] - cpu["mean"]["ssim"]) < 1e-4


def _stopped_demo_fit(tmp_path, device: str, kernel: str = "learned"):
    """A demo-scene fit on ``device`` interrupted at iteration 100 of 200: (scene, run, config)."""
    scene = make_demo_scene(tmp_path / "demo", num_views=8, size=32)
    train = TrainConfig(iters=200, budget=400, device=device)
    cfg = FitConfig(kernel=kernel, sh_degree=1, device=device, backend="auto", train=train)
    scale_schedules_to_run(cfg)
    run, calls = tmp_path / "run", {"n": 0}

    def ctrl_c():
        calls["n"] += 1
        if calls["n"] == 100:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        run_fit(scene, run, cfg, should_stop=ctrl_c)
    return scene, run, cfg


def test_resume_takes_a_checkpoint_whose_mcmc_generator_is_another_devices(tmp_path):
    """A GPU's generator keeps a 16-byte state where the CPU's keeps 5,056 bytes: resuming on
    the CPU a run that a GPU wrote (here: its checkpoint given such a state) goes on, draws from
    a stream the seed and the iteration fix, and says so in the run's events."""
    scene, run, cfg = _stopped_demo_fit(tmp_path, "cpu")
    ckpt = run / "checkpoints" / "last.pt"
    state = torch.load(ckpt, weights_only=True)
    state["trainer"]["mcmc_gen"] = torch.zeros(16, dtype=torch.uint8)
    torch.save(state, ckpt)
    stopped_at = state["trainer"]["it"]
    run_fit(scene, run, cfg, resume=True)
    summary = json.loads((run / "fit.json").read_text())
    assert summary["iterations"] == 200
    moved = [e for e in summary["events"] if e["event"] == "device_changed"]
    assert [e["iteration"] for e in moved] == [stopped_at]
    assert summary["machine"]["cpu"] and summary["machine"]["logical_cpus"] >= 1  # which CPU trained it


@cuda
@pytest.mark.parametrize("first, then", [("cuda", "cpu"), ("cpu", "cuda")])
def test_a_run_goes_on_on_another_device(first, then, tmp_path):
    """`fit --resume --device D` moves a stopped run between the GPU and the CPU: the checkpoint
    loads whatever device wrote it, and the run finishes and learns on the other one."""
    scene, run, _ = _stopped_demo_fit(tmp_path, first)
    stopped_at = torch.load(run / "checkpoints" / "last.pt", weights_only=True)["trainer"]["it"]
    run_fit(scene, run, None, resume=True, resume_options={"device": then})
    summary = json.loads((run / "fit.json").read_text())
    assert summary["iterations"] == 200
    assert [e["iteration"] for e in summary["events"] if e["event"] == "device_changed"] == [stopped_at]
    psnr = run_eval(run, ("psnr",), device="cpu", backend="torch")["mean"]["psnr"]
    # 200 iterations of the learned kernel take the demo scene from 10.6 to 12.5 dB on the CPU
    assert psnr > summary["initial_psnr"] + 1.0, (summary["initial_psnr"], psnr)


@cuda
def test_budget_auto_on_cuda(tmp_path):
    """--budget auto's short runs, held-out renders, compaction and prune run on the GPU."""
    scene = make_demo_scene(tmp_path / "demo", num_views=8, size=32)
    auto = AutoBudgetConfig(start_fraction=0.125, max_factor=1.0, threshold_db=-100.0, stage_share=0.2)
    train = TrainConfig(iters=100, budget=400, init="random", device="cuda", mcmc=MCMCConfig(refine_every=1, refine_start=0))
    run = run_fit(scene, tmp_path / "run", FitConfig(sh_degree=1, device="cuda", auto_budget=auto, train=train)).path
    rep = json.loads((run / "fit.json").read_text())["auto_budget"]
    assert rep["chosen_budget"] == 400 and "compact" in rep and "prune" in rep


@cuda
@pytest.mark.parametrize("kernel", ["gaussian", "gabor", "learned"])
def test_image_fit_on_cuda_matches_the_cpu_torch_run(kernel):
    """The same seed gives the same splats on both devices; 60 steps later the two fits agree
    to within float32 drift."""
    y, x = torch.meshgrid(torch.linspace(0, 1, 24), torch.linspace(0, 1, 32), indexing="ij")
    target = torch.stack([0.5 + 0.4 * torch.sin(6 * x), 0.5 + 0.4 * torch.cos(5 * y), 0.3 + 0.5 * x * y], -1)
    fits = {}
    for dev in ("cpu", "cuda"):
        cfg = ImageFitConfig(kernel=kernel, budget_bytes=4096, iters=60, backend="torch", device=dev,
                             shapes=8, shape_start=0.5, lpips=False)
        model, _ = fit_image(target, cfg)
        assert next(model.parameters()).device.type == "cpu"  # handed back for saving
        with torch.no_grad():
            fits[dev] = float(((model.render().clamp(0, 1) - target) ** 2).mean())
    assert fits["cuda"] < 0.01
    assert fits["cuda"] == pytest.approx(fits["cpu"], rel=0.05)
