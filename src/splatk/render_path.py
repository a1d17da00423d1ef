"""Camera paths for videos: smooth interpolation through the train cameras."""
from __future__ import annotations

import math

import torch

from .data.types import Camera


def _slerp(q0: torch.Tensor, q1: torch.Tensor, t: float) -> torch.Tensor:
    d = float((q0 * q1).sum())
    if d < 0:
        q1, d = -q1, -d
    if d > 0.9995:
        q = q0 + t * (q1 - q0)
        return q / q.norm()
    th = math.acos(d)
    return (math.sin((1 - t) * th) * q0 + math.sin(t * th) * q1) / math.sin(th)


def _rot_to_quat(R: torch.Tensor) -> torch.Tensor:
    R = R.double()
    w = math.sqrt(max(0.0, 1 + R[0, 0] + R[1, 1] + R[2, 2])) / 2
    x = math.copysign(math.sqrt(max(0.0, 1 + R[0, 0] - R[1, 1] - R[2, 2])) / 2, float(R[2, 1] - R[1, 2]))
    y = math.copysign(math.sqrt(max(0.0, 1 - R[0, 0] + R[1, 1] - R[2, 2])) / 2, float(R[0, 2] - R[2, 0]))
    z = math.copysign(math.sqrt(max(0.0, 1 - R[0, 0] - R[1, 1] + R[2, 2])) / 2, float(R[1, 0] - R[0, 1]))
    q = torch.tensor([w, x, y, z], dtype=torch.float64)
    return q / q.norm()


def _quat_to_rot(q: torch.Tensor) -> torch.Tensor:
    w, x, y, z = q.tolist()
    return torch.tensor([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ], dtype=torch.float64)


def interpolate_cameras(cameras: list[Camera], num_frames: int) -> list[Camera]:
    """``num_frames`` cameras along the train cameras (in name order), rotations slerped."""
    cams = sorted(cameras, key=lambda c: c.name)
    if len(cams) < 2 or num_frames <= 0:
        return list(cams[:num_frames])
    out = []
    for f in range(num_frames):
        s = f / num_frames * (len(cams) - 1)
        i = min(int(s), len(cams) - 2)
        t = s - i
        a, b = cams[i], cams[i + 1]
        q = _slerp(_rot_to_quat(a.world_to_cam[:3, :3].T), _rot_to_quat(b.world_to_cam[:3, :3].T), t)
        c2w_R = _quat_to_rot(q)
        centre = (1 - t) * a.center.double() + t * b.center.double()
        w2c = torch.eye(4, dtype=torch.float64)
        w2c[:3, :3] = c2w_R.T
        w2c[:3, 3] = -c2w_R.T @ centre
        out.append(Camera(f"path_{f:04d}", a.width, a.height, a.fx, a.fy, a.cx, a.cy, w2c.float()))
    return out
