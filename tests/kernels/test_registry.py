"""One kernel registry keyed by (primitive, name): every kernel is found by its primitive type,
a new one is one class plus its registration, and a name a primitive type lacks is an error
that names the kernels it has."""
import pytest
import torch

from splatk.backends import PlanarProfile, Profile
from splatk.errors import InputError
from splatk.kernels import KERNELS, Kernel, kernel_names, make_kernel, register_kernel
from splatk.kernels.planar import PlanarKernel


def test_each_primitive_lists_its_own_kernels():
    assert kernel_names("volumetric") == ["beta", "gaussian", "learned", "student_t"]
    assert kernel_names("planar") == ["gaussian", "learned"]
    assert kernel_names() == ["beta", "gaussian", "learned", "student_t"]
    assert kernel_names("voxel") == []


@pytest.mark.parametrize("primitive", ["volumetric", "planar"])
@pytest.mark.parametrize("name", ["gaussian", "learned"])
def test_make_kernel_builds_the_kernel_of_that_primitive(primitive, name):
    kernel = make_kernel(name, primitive, **({"weights": "none"} if name == "learned" else {}))
    assert isinstance(kernel, KERNELS[(primitive, name)])
    assert (kernel.primitive, kernel.name) == (primitive, name)
    assert isinstance(kernel, PlanarKernel) == (primitive == "planar")


def test_the_two_gaussians_are_different_kernels():
    assert make_kernel("gaussian").profile({"means": torch.zeros(3, 3)}, None) == Profile("gaussian")
    assert make_kernel("gaussian", "planar").profile({}, None) == PlanarProfile("gaussian_surfel")


def test_a_kernel_a_primitive_lacks_is_an_error_naming_its_kernels():
    with pytest.raises(InputError, match="kernel 'beta' has no planar version.*gaussian or learned"):
        make_kernel("beta", "planar")
    with pytest.raises(ValueError, match="unknown kernel 'cosine'; choose from beta, gaussian"):
        make_kernel("cosine")
    with pytest.raises(ValueError, match="unknown primitive type 'voxel'"):
        make_kernel("gaussian", "voxel")


def test_a_volumetric_only_option_is_an_input_error_for_a_planar_kernel():
    assert make_kernel("learned", k=4, weights="none").k == 4
    with pytest.raises(InputError, match="planar kernel 'learned'.*drop volumetric-only kernel options"):
        make_kernel("learned", "planar", k=4, weights="none")


def test_a_new_kernel_is_one_class_and_its_registration(monkeypatch):
    monkeypatch.setattr("splatk.kernels.base.KERNELS", dict(KERNELS))  # leave the registry as found

    @register_kernel
    class SquareSurfel(PlanarKernel):
        name = "square"

        def profile(self, prims, view):
            return PlanarProfile("grid", torch.ones(len(prims["means"]), 4, 4))

    assert kernel_names("planar") == ["gaussian", "learned", "square"]
    assert "square" not in kernel_names("volumetric")
    kernel = make_kernel("square", "planar")
    assert isinstance(kernel, SquareSurfel) and isinstance(kernel, Kernel)
    assert kernel.profile({"means": torch.zeros(2, 3)}, None).table.shape == (2, 4, 4)
    with pytest.raises(ValueError, match="unknown kernel 'square'"):
        make_kernel("square")


def test_beta_gaussian_bake_matches_the_profiles_second_moment():
    """Export's Gaussian for a Beta splat has the profile's per-axis variance over the unit disk."""
    import torch

    from splatk.kernels import make_kernel

    kernel = make_kernel("beta", "volumetric")
    beta = torch.tensor([0.1, 1.0, 4.0, 20.0])
    prims = {"beta_raw": torch.log(beta / 4.0)[:, None]}
    s = kernel.gaussian_scale_factor(prims)
    r = torch.linspace(0, 1, 200001, dtype=torch.float64)[:, None]
    w = (1 - r ** 2).clamp_min(0) ** beta.double() * r  # radial weight on the disk
    var_per_axis = 0.5 * torch.trapezoid(r ** 2 * w, r, dim=0) / torch.trapezoid(w, r, dim=0)
    assert torch.allclose(s.double() ** 2, var_per_axis, rtol=1e-3), (s ** 2, var_per_axis)
