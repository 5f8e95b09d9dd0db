"""Small textured scenes with known cameras, for the structure-from-motion tests and scripts/bench_poses.py.

A cube [-1, 1]^3 standing on a ground square z = -1, |x|, |y| <= 4, both covered in a random
two-scale block texture (plenty of corners for SIFT); cameras on a ring looking at the origin
(OpenGL camera-to-world, as nerfmeta uses). Ray casting is exact (slabs and a plane) with 2 x 2
supersampling; rays that hit nothing see white. Pure numpy, deterministic for a seed.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
from PIL import Image

CUBE = 1.0
GROUND = 4.0


def look_at(eye: np.ndarray, target: np.ndarray, up: np.ndarray = np.array([0.0, 0.0, 1.0])) -> np.ndarray:
    """(4, 4) OpenGL camera-to-world pose at ``eye`` looking at ``target`` (camera -z towards it)."""
    back = eye - target
    back = back / np.linalg.norm(back)
    right = np.cross(up, back)
    right = right / np.linalg.norm(right)
    pose = np.eye(4)
    pose[:3, :3] = np.stack([right, np.cross(back, right), back], axis=1)
    pose[:3, 3] = eye
    return pose


def ring_poses(n: int, radius: float = 4.5, elevation_deg: float = 30.0, turn: float = 1.0) -> np.ndarray:
    """(n, 4, 4) cameras evenly spaced over ``turn`` of a circle around the z axis, looking at the origin."""
    el = math.radians(elevation_deg)
    poses = []
    for k in range(n):
        az = 2 * math.pi * turn * k / n
        eye = radius * np.array([math.cos(az) * math.cos(el), math.sin(az) * math.cos(el), math.sin(el)])
        poses.append(look_at(eye, np.zeros(3)))
    return np.stack(poses)


def _texture(points: np.ndarray, table: np.ndarray) -> np.ndarray:
    """(N, 3) colours in [0, 1] of surface points: random blocks at 4 and 12 cells per unit."""
    colour = np.zeros((len(points), 3))
    for cells, weight, salt in ((4.0, 0.55, 0), (12.0, 0.45, 7)):
        idx = np.floor(points * cells + 1e-6).astype(np.int64)
        key = (idx[:, 0] * 73856093) ^ (idx[:, 1] * 19349663) ^ (idx[:, 2] * 83492791) ^ salt
        colour += weight * table[np.mod(key, len(table))]
    return colour


def render(poses: np.ndarray, focal: float, height: int, width: int, seed: int = 0) -> np.ndarray:
    """(n, height, width, 3) uint8 views of the textured cube on the textured ground."""
    table = np.random.default_rng(seed).random((4096, 3))
    offsets = np.array([[0.25, 0.25], [0.75, 0.25], [0.25, 0.75], [0.75, 0.75]])
    cols, rows = np.meshgrid(np.arange(width), np.arange(height))
    images = []
    for pose in poses:
        acc = np.zeros((height * width, 3))
        for ox, oy in offsets:
            x = (cols.reshape(-1) + ox - width / 2) / focal
            y = -(rows.reshape(-1) + oy - height / 2) / focal
            dirs = np.stack([x, y, -np.ones_like(x)], 1) @ pose[:3, :3].T
            origin = pose[:3, 3]
            with np.errstate(divide="ignore", invalid="ignore"):
                t0 = (-CUBE - origin) / dirs
                t1 = (CUBE - origin) / dirs
                t_near = np.nanmax(np.minimum(t0, t1), axis=1)
                t_far = np.nanmin(np.maximum(t0, t1), axis=1)
                t_cube = np.where((t_near <= t_far) & (t_near > 0), t_near, np.inf)
                t_ground = (-CUBE - origin[2]) / dirs[:, 2]
            p_ground = origin + t_ground[:, None] * dirs
            on_ground = (t_ground > 0) & (np.abs(p_ground[:, 0]) <= GROUND) & (np.abs(p_ground[:, 1]) <= GROUND)
            t_ground = np.where(on_ground, t_ground, np.inf)
            t = np.minimum(t_cube, t_ground)
            hit = np.isfinite(t)
            colour = np.ones((len(t), 3))
            points = origin + t[hit, None] * dirs[hit]
            shade = np.where(t_cube[hit] <= t_ground[hit], 1.0, 0.8)[:, None]
            colour[hit] = _texture(points, table) * shade
            acc += colour
        images.append((acc / len(offsets) * 255 + 0.5).clip(0, 255).astype(np.uint8).reshape(height, width, 3))
    return np.stack(images)


def write_photos(folder: Path, images: np.ndarray, *, suffix: str = ".png") -> list[Path]:
    """Write ``images`` as ``view_000.png`` ... into ``folder``; the paths."""
    folder.mkdir(parents=True, exist_ok=True)
    paths = []
    for k, image in enumerate(images):
        path = folder / f"view_{k:03d}{suffix}"
        Image.fromarray(image).save(path)
        paths.append(path)
    return paths


def write_blender(folder: Path, images: np.ndarray, poses: np.ndarray, focal: float) -> None:
    """The same views as a nerfstudio scene with their true poses (``transforms.json``)."""
    write_photos(folder / "images", images)
    h, w = images.shape[1:3]
    frames = [{"file_path": f"images/view_{k:03d}.png", "transform_matrix": pose.tolist()} for k, pose in enumerate(poses)]
    doc = {"fl_x": focal, "fl_y": focal, "cx": w / 2, "cy": h / 2, "w": w, "h": h, "frames": frames}
    (folder / "transforms.json").write_text(json.dumps(doc))


def umeyama(source: np.ndarray, target: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """``(s, R, t)`` minimising ``sum |s R source_i + t - target_i|^2`` (Umeyama 1991); source, target: (n, 3)."""
    mu_s, mu_t = source.mean(0), target.mean(0)
    a, b = source - mu_s, target - mu_t
    cov = b.T @ a / len(source)
    u, d, vt = np.linalg.svd(cov)
    sign = np.eye(3)
    if np.linalg.det(u) * np.linalg.det(vt) < 0:
        sign[2, 2] = -1
    rotation = u @ sign @ vt
    scale = float(np.trace(np.diag(d) @ sign) / (a**2).sum(1).mean())
    return scale, rotation, mu_t - scale * rotation @ mu_s


def pose_errors(estimated: np.ndarray, true: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per view ``(rotation error in degrees, camera-centre distance)`` of (n, 4, 4) camera-to-world poses
    after the similarity that best maps the estimated centres onto the true ones."""
    s, rotation, t = umeyama(estimated[:, :3, 3], true[:, :3, 3])
    centres = (s * estimated[:, :3, 3] @ rotation.T) + t
    rot_est = rotation @ estimated[:, :3, :3]
    rel = np.einsum("nji,njk->nik", rot_est, true[:, :3, :3])
    cos = np.clip((np.trace(rel, axis1=1, axis2=2) - 1) / 2, -1, 1)
    return np.degrees(np.arccos(cos)), np.linalg.norm(centres - true[:, :3, 3], axis=1)
