"""Tiny generated scenes for unit tests (no files, no ../shared)."""
from __future__ import annotations

import math
from pathlib import Path

import torch

from splatk import backends
from splatk.data.types import Camera, Scene
from splatk.models.volumetric import SplatModel

SHARED_DATA = Path(__file__).resolve().parents[2] / "shared" / "data"


def look_at(center, target=(0.0, 0.0, 0.0), up=(0.0, 0.0, 1.0)) -> torch.Tensor:
    """World->camera [4, 4] (OpenCV axes) for a camera at ``center`` looking at ``target``."""
    c = torch.tensor(center, dtype=torch.float64)
    f = torch.tensor(target, dtype=torch.float64) - c
    f = f / f.norm()
    r = torch.linalg.cross(f, torch.tensor(up, dtype=torch.float64))
    r = r / r.norm()
    d = torch.linalg.cross(f, r)
    R = torch.stack([r, d, f])  # rows: camera x (right), y (down), z (forward)
    M = torch.eye(4, dtype=torch.float64)
    M[:3, :3] = R
    M[:3, 3] = -R @ c
    return M.float()


def orbit_cameras(n: int, size: int = 48, radius: float = 4.0, fov_deg: float = 50.0) -> list[Camera]:
    f = 0.5 * size / math.tan(math.radians(fov_deg) / 2)
    cams = []
    for i in range(n):
        a = 2 * math.pi * i / n
        c = (radius * math.cos(a), radius * math.sin(a), 1.2 + 0.5 * math.sin(3 * a))
        cams.append(Camera(f"view_{i:03d}.png", size, size, f, f, size / 2, size / 2, look_at(c)))
    return cams


def random_model(n: int = 60, seed: int = 0, kernel: str = "gaussian") -> SplatModel:
    g = torch.Generator().manual_seed(seed)
    pts = (torch.rand(n, 3, generator=g) * 2 - 1) * 0.8
    cols = torch.rand(n, 3, generator=g)
    model = SplatModel.from_points(pts, cols, kernel=kernel, color="sh", color_options={"sh_degree": 1})
    with torch.no_grad():
        model.prims["log_scales"].data[:] = math.log(0.15) + 0.3 * torch.randn(n, 3, generator=g)
        model.prims["quats"].data[:] = torch.randn(n, 4, generator=g)
        model.prims["opacity_logits"].data[:] = 1.0 + torch.randn(n, generator=g)
    return model


def synthetic_scene(num_views: int = 12, size: int = 48, seed: int = 0, num_points: int = 60) -> Scene:
    """Cameras around a random Gaussian 'object'; images rendered by the torch reference.
    Every 4th view is a test view. SfM points = noisy copies of the true centres."""
    gt = random_model(num_points, seed)
    bg = (1.0, 1.0, 1.0)
    cams = orbit_cameras(num_views, size)
    with torch.no_grad():
        for cam in cams:
            img = gt.render(cam, torch.tensor(bg), sh_degree=1, backend=backends.get("torch")).image
            cam.image = (img.clamp(0, 1) * 255 + 0.5).to(torch.uint8)
    g = torch.Generator().manual_seed(seed + 7)
    pts = gt.prims["means"].detach() + 0.05 * torch.randn(num_points, 3, generator=g)
    cols = torch.rand(num_points, 3, generator=g)
    test = [c for i, c in enumerate(cams) if i % 4 == 0]
    train = [c for i, c in enumerate(cams) if i % 4 != 0]
    return Scene(Path("synthetic"), train, test, pts, cols, bg, "synthetic")


def synthetic_photo(h: int = 24, w: int = 32) -> torch.Tensor:
    """[h, w, 3] smooth colour waves with a hard-edged red disk: a photo for the 2D image fits."""
    y, x = torch.meshgrid(torch.linspace(0, 1, h), torch.linspace(0, 1, w), indexing="ij")
    img = torch.stack([0.5 + 0.4 * torch.sin(6 * x), 0.5 + 0.4 * torch.cos(5 * y), 0.3 + 0.5 * x * y], -1)
    img[(x - 0.5) ** 2 + (y - 0.5) ** 2 < 0.05] = torch.tensor([0.9, 0.2, 0.1])
    return img
