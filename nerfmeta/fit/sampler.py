"""Training rays: seeded random pixels from the training views, rays computed per batch."""

from __future__ import annotations

import torch

from nerfmeta.data.scene import RayBatch, Scene
from nerfmeta.render.rays import camera_rays, image_rays


class RaySampler:
    """Draws random training pixels (uniformly over all pixels of all views of a split).

    Rays are built per batch from the pose and intrinsics of each pixel's view, so memory holds
    only the images, not one ray per pixel.
    """

    def __init__(self, scene: Scene, split: str, device: torch.device | str):
        idx = scene.split_indices(split)
        if len(idx) == 0:
            raise ValueError(f"scene has no '{split}' views")
        self.images = scene.images[idx].to(device)
        self.alphas = None if scene.alphas is None else scene.alphas[idx].to(device)
        self.poses = scene.poses[idx].to(device)
        self.intrinsics = scene.intrinsics[idx].to(device)
        self.near, self.far = float(scene.near), float(scene.far)
        self.n_views, self.height, self.width = self.images.shape[:3]

    @property
    def n_pixels(self) -> int:
        return self.n_views * self.height * self.width

    def sample(self, n_rays: int, generator: torch.Generator) -> RayBatch:
        """A batch of ``n_rays`` random training rays with their target colours."""
        flat = torch.randint(self.n_pixels, (n_rays,), generator=generator).to(self.images.device)
        hw = self.height * self.width
        view, pix = flat // hw, flat % hw
        row, col = pix // self.width, pix % self.width
        dtype = self.poses.dtype
        xy = torch.stack([col.to(dtype) + 0.5, row.to(dtype) + 0.5], -1)
        origins, dirs = camera_rays(self.poses[view], self.intrinsics[view], xy)
        target = self.images[view, row, col]
        near = torch.full((n_rays,), self.near, dtype=dtype, device=origins.device)
        far = torch.full((n_rays,), self.far, dtype=dtype, device=origins.device)
        alpha = None if self.alphas is None else self.alphas[view, row, col]
        return RayBatch(origins, dirs, near, far, target, alpha)


def view_rays(scene: Scene, view: int, device: torch.device | str) -> RayBatch:
    """All pixel rays of one view, row-major, with the view's image as target."""
    pose, intr = scene.poses[view].to(device), scene.intrinsics[view].to(device)
    origins, dirs = image_rays(pose, intr, scene.height, scene.width)
    n = scene.height * scene.width
    near = torch.full((n,), float(scene.near), dtype=pose.dtype, device=device)
    far = torch.full((n,), float(scene.far), dtype=pose.dtype, device=device)
    target = scene.images[view].to(device).reshape(n, 3)
    return RayBatch(origins.reshape(n, 3), dirs.reshape(n, 3), near, far, target)
