"""`splatk export --format kernels`: profile and d1-histogram figures plus kernels.json."""
import json

import pytest
import torch

from splatk.models.io import load_model, model_spec, save_model
from splatk.stages.kernel_plots import export_kernel_plots, view_profiles
from tests.scenes import random_model


PNG = b"\x89PNG\r\n\x1a\n"


def make_run(tmp_path, kernel):
    model = random_model(30, 0, kernel=kernel)
    if kernel == "learned":
        g = torch.Generator().manual_seed(0)
        with torch.no_grad():
            model.prims["z3d"].data[:] = torch.randn(30, 5, generator=g)
    run = tmp_path / f"run_{kernel}"
    # the scene folder does not exist: the figures fall back to an orbit of cameras
    save_model(model, run / "model.pt", model_spec(model, {}, {"sh_degree": 1}),
               {"scene": str(tmp_path / "no_scene"), "background": [1.0, 1.0, 1.0]})
    return run


@pytest.mark.parametrize("kernel", ["learned", "gaussian", "beta"])
def test_export_kernel_plots(tmp_path, kernel):
    run = make_run(tmp_path, kernel)
    out = export_kernel_plots(run, tmp_path / "plots", backend="torch", num_views=3, num_primitives=2)
    for name in ("profiles.png", "d1_histograms.png"):
        assert (out / name).read_bytes()[:8] == PNG
    doc = json.loads((out / "kernels.json").read_text())
    assert doc["kernel"] == kernel and doc["views_source"] == "orbit"
    assert len(doc["views"]) == 3 and len(doc["primitives"]) == 2
    model, _ = load_model(run / "model.pt")
    from splatk.stages.kernel_plots import orbit_cameras

    cams = orbit_cameras(model.prims["means"].detach(), 3)
    for v, cam in zip(doc["views"], cams):
        idx, prof, _ = view_profiles(model, cam)
        assert v["num_visible"] == len(idx) > 0
        assert sum(v["d1"]["hist_counts"]) == len(idx)
        if kernel == "learned":  # d1 = Phi_dec(0, z2d) = the first table sample
            assert v["d1"]["mean"] == pytest.approx(float(prof.params[:, 0].mean()), abs=1e-6)
        else:  # fixed kernels peak at 1
            assert v["d1"]["mean"] == pytest.approx(1.0)
    prim = doc["primitives"][0]
    some_view = next(iter(prim["views"].values()))
    assert len(some_view["profile"]) == len(doc["radii"])
    if kernel == "learned":
        assert len(some_view["samples"]) == 2 and len(some_view["phi_dec"]) == len(doc["radii"])
        # the drawn profile is the interpolated table: its ends are the samples
        assert some_view["profile"][0] == pytest.approx(some_view["samples"][0], abs=1e-4)
        assert some_view["profile"][-1] == pytest.approx(some_view["samples"][-1], abs=1e-4)
