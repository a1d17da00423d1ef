"""Camera paths for videos: interpolation through cameras, an orbit or a spiral around the train
cameras' look-at centre, and path files."""
from __future__ import annotations

import json
import math
from pathlib import Path

import torch

from .data.types import Camera
from .errors import InputError


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


# Camera frames below use OpenCV axes (x right, y down, z forward), as Camera does; "up" is the
# world direction the cameras' -y axes share on average.

def _centres_and_axes(cameras: list[Camera]) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """([N, 3] centres, [N, 3] viewing directions, [3] mean up), float64."""
    R_c2w = torch.stack([c.world_to_cam[:3, :3].double().T for c in cameras])
    centres = torch.stack([c.center.double() for c in cameras])
    up = -R_c2w[:, :, 1].mean(0)
    return centres, R_c2w[:, :, 2], up / up.norm()


def look_at_centre(cameras: list[Camera]) -> torch.Tensor:
    """[3] the point nearest every camera's optical axis in the least-squares sense (mip-NeRF
    360's ``focus_point_fn``); for cameras whose axes barely cross (all facing one way) or that
    look away from it, a point ahead of the mean camera at the cameras' spread instead."""
    centres, dirs, _ = _centres_and_axes(cameras)
    eye = torch.eye(3, dtype=torch.float64)
    proj = eye - dirs[:, :, None] * dirs[:, None, :]  # [N, 3, 3]: onto the plane normal to each axis
    A, b = proj.sum(0), (proj @ centres[:, :, None]).sum(0).squeeze(-1)
    if torch.linalg.cond(A) < 1e6:
        p = torch.linalg.solve(A, b)
        if float(((p - centres) * dirs).sum(-1).mean()) > 0:  # in front of the cameras
            return p
    mean_dir = dirs.mean(0)
    spread = float((centres - centres.mean(0)).norm(dim=-1).mean()) or 1.0
    return centres.mean(0) + mean_dir / mean_dir.norm() * spread


def look_at(eye: torch.Tensor, target: torch.Tensor, up: torch.Tensor) -> torch.Tensor:
    """[4, 4] world -> camera transform of a camera at ``eye`` looking at ``target``, its -y axis
    as close to ``up`` as the view direction allows."""
    z = target - eye
    z = z / z.norm()
    x = torch.linalg.cross(-up, z)
    if float(x.norm()) < 1e-9:  # looking straight up or down: any right vector will do
        x = torch.linalg.cross(torch.tensor([1.0, 0.0, 0.0], dtype=z.dtype), z)
    x = x / x.norm()
    y = torch.linalg.cross(z, x)
    R_c2w = torch.stack([x, y, z], 1)
    w2c = torch.eye(4, dtype=torch.float64)
    w2c[:3, :3] = R_c2w.T
    w2c[:3, 3] = -R_c2w.T @ eye
    return w2c


def _like(cam: Camera, name: str, w2c: torch.Tensor) -> Camera:
    return Camera(name, cam.width, cam.height, cam.fx, cam.fy, cam.cx, cam.cy, w2c.float())


def orbit_path(cameras: list[Camera], num_frames: int) -> list[Camera]:
    """A full circle around the look-at centre about the mean up axis, at the cameras' mean
    height above the centre and mean horizontal distance from it, starting at the first camera
    (name order) and looking at the centre; intrinsics of that camera."""
    cams = sorted(cameras, key=lambda c: c.name)
    centres, _, up = _centres_and_axes(cams)
    centre = look_at_centre(cams)
    offsets = centres - centre
    heights = offsets @ up
    flat = offsets - heights[:, None] * up
    radius = float(flat.norm(dim=-1).mean())
    e1 = flat[0] / flat[0].norm() if float(flat[0].norm()) > 1e-9 else torch.linalg.cross(up, offsets[0])
    e1 = e1 / e1.norm()
    e2 = torch.linalg.cross(up, e1)
    out = []
    for f in range(num_frames):
        t = 2 * math.pi * f / num_frames
        eye = centre + float(heights.mean()) * up + radius * (math.cos(t) * e1 + math.sin(t) * e2)
        out.append(_like(cams[0], f"orbit_{f:04d}", look_at(eye, centre, up)))
    return out


def spiral_path(cameras: list[Camera], num_frames: int, rots: float = 2.0, zrate: float = 0.5,
                radius: float = 0.15) -> list[Camera]:
    """nerfstudio's ``get_spiral_path`` about the first camera (name order): the eye moves through
    ``[r cos t, -r sin t, -r sin(zrate t)]`` in that camera's frame, t over ``rots`` turns, ``r``
    = ``radius`` x the camera's distance to the look-at centre, always looking at that centre."""
    cams = sorted(cameras, key=lambda c: c.name)
    centre = look_at_centre(cams)
    ref = cams[0]
    R_c2w = ref.world_to_cam[:3, :3].double().T
    origin = ref.center.double()
    up = -R_c2w[:, 1]
    r = radius * float((centre - origin).norm())
    out = []
    for f in range(num_frames):
        t = 2 * math.pi * rots * f / num_frames
        eye = origin + R_c2w @ torch.tensor([r * math.cos(t), -r * math.sin(t), -r * math.sin(zrate * t)],
                                            dtype=torch.float64)
        out.append(_like(ref, f"spiral_{f:04d}", look_at(eye, centre, up)))
    return out


PATH_FILE_FIELDS = ("fx", "fy", "cx", "cy", "width", "height")
PATH_FILE_HINT = ('a JSON list of {"world_to_cam" or "camera_to_world": 4x4 (OpenCV axes), "fx", "fy", '
                  '"cx", "cy", "width", "height"}')


def cameras_from_json(path: Path) -> list[Camera]:
    """The cameras of a path file, in its order: a JSON list of objects with ``world_to_cam``
    or ``camera_to_world`` (4x4, OpenCV axes: x right, y down, z forward) and the pinhole
    ``fx, fy, cx, cy, width, height`` in pixels.

    Raises:
        InputError: the file is not such a list (names the entry and the field).
    """
    try:
        entries = json.loads(Path(path).read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
        raise InputError(path, f"not a readable JSON file ({e})", PATH_FILE_HINT) from None
    if not isinstance(entries, list) or not entries:
        raise InputError(path, "a camera path is a non-empty JSON list", PATH_FILE_HINT)
    cams = []
    for i, e in enumerate(entries):
        if not isinstance(e, dict):
            raise InputError(path, f"entry {i} is not an object", PATH_FILE_HINT)
        missing = [k for k in PATH_FILE_FIELDS if k not in e]
        if missing or ("world_to_cam" in e) == ("camera_to_world" in e):
            what = f"lacks {', '.join(missing)}" if missing else "needs exactly one of world_to_cam, camera_to_world"
            raise InputError(path, f"entry {i} {what}", PATH_FILE_HINT)
        key = "world_to_cam" if "world_to_cam" in e else "camera_to_world"
        try:
            m = torch.tensor(e[key], dtype=torch.float64)
            fx, fy, cx, cy = (float(e[k]) for k in ("fx", "fy", "cx", "cy"))
            width, height = int(e["width"]), int(e["height"])
        except (TypeError, ValueError) as err:
            raise InputError(path, f"entry {i}: {err}", PATH_FILE_HINT) from None
        if m.shape != (4, 4) or not torch.isfinite(m).all() or abs(float(torch.linalg.det(m[:3, :3]))) < 1e-9:
            raise InputError(path, f"entry {i}: {key} is not an invertible 4x4 matrix", PATH_FILE_HINT)
        if min(width, height) < 1 or min(fx, fy) <= 0:
            raise InputError(path, f"entry {i}: width, height, fx and fy must be positive", PATH_FILE_HINT)
        w2c = m if key == "world_to_cam" else torch.linalg.inv(m)
        cams.append(Camera(f"path_{i:04d}", width, height, fx, fy, cx, cy, w2c.float()))
    return cams
