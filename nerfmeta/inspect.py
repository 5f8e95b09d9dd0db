"""Inspecting a scene: a typed summary, its text form, and a 3-D plot of the cameras.

``inspect_scene`` is what ``nerfmeta inspect`` calls. It loads and summarises the scene before
writing anything, so a bad scene leaves no output folder behind.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import torch
from matplotlib.figure import Figure

from nerfmeta.data.common import LoadOptions
from nerfmeta.data.normalize import describe
from nerfmeta.data.registry import load_scene_with
from nerfmeta.data.scene import Normalization, Scene
from nerfmeta.data.sfm import folded_walk_note, walk_jumps
from nerfmeta.paths import check_output_folder, os_errors_named
from nerfmeta.io import atomic_path, write_json
from nerfmeta.render.rays import frustum_corners

SPLIT_COLOURS = {"train": "tab:blue", "val": "tab:green", "test": "tab:red"}
FRUSTUM_DEPTH_FRACTION = 0.1
"""Frusta are drawn this fraction of the plotted extent (cameras and bounds) deep."""


@dataclass(frozen=True)
class SceneSummary:
    """What ``nerfmeta inspect`` reports about a scene."""

    format: str
    """Parser that read the scene."""
    source: str
    """Folder or file it was read from."""
    n_views: int
    """Number of views in all splits."""
    views_per_split: dict[str, int]
    """Split name -> number of views."""
    holdout: str
    """How the test split was chosen."""
    height: int
    """Image height in pixels, as loaded."""
    width: int
    """Image width in pixels, as loaded."""
    downscale: float
    """Factor the images were reduced by."""
    focal: tuple[float, float]
    """Median ``(fx, fy)`` in pixels."""
    principal_point: tuple[float, float]
    """Median ``(cx, cy)`` in pixels."""
    intrinsics_vary: bool
    """True when the views do not all share the same intrinsics."""
    near: float
    """Ray distance where sampling starts."""
    far: float
    """Ray distance where sampling ends."""
    near_far_source: str
    """Where ``near``/``far`` came from: the file, the format's default, or derived from the cameras."""
    bounds: tuple[tuple[float, float, float], tuple[float, float, float]]
    """Axis-aligned box ``(min_xyz, max_xyz)`` holding the content."""
    category: str | None
    """Scene category when the files give one."""
    background: tuple[float, float, float] | None
    """RGB the alpha channel was composited on; None for opaque images."""
    camera_distance: tuple[float, float, float]
    """Min, median and max distance from the camera centres to the centre of ``bounds``."""
    scene_type: dict[str, str | bool]
    """Kind of capture (object, forward, unbounded) and why (:mod:`nerfmeta.data.scene_type`)."""
    normalization: dict[str, float | list[float]]
    """What loading applied, ``{"scale", "offset"}`` with ``loaded = scale * file + offset``;
    ``near``, ``far``, ``bounds`` and ``camera_distance`` above are in the loaded frame."""
    pose_jumps: list[int]
    """Views (file order) of a walk whose camera turns by more than 90 degrees from the previous view: where the poses
    folded a video's walk (:func:`nerfmeta.data.sfm.walk_jumps`); empty for photos in no particular order."""


def summarize_scene(scene: Scene) -> SceneSummary:
    """The summary of a loaded scene (pure)."""
    intr = scene.intrinsics.double()
    med = intr.median(dim=0).values
    centre = scene.bounds.double().mean(dim=0)
    dist = torch.linalg.vector_norm(scene.poses[:, :3, 3].double() - centre, dim=-1)
    bounds = scene.bounds.double()
    return SceneSummary(
        format=scene.format,
        source=os.fspath(scene.source),
        n_views=scene.n_views,
        views_per_split={k: len(v) for k, v in scene.splits.items()},
        holdout=scene.holdout,
        height=scene.height,
        width=scene.width,
        downscale=float(scene.downscale),
        focal=(float(med[0]), float(med[1])),
        principal_point=(float(med[2]), float(med[3])),
        intrinsics_vary=bool((intr - intr[:1]).abs().max() > 1e-6),
        near=float(scene.near),
        far=float(scene.far),
        near_far_source=scene.near_far_source,
        bounds=(tuple(float(v) for v in bounds[0]), tuple(float(v) for v in bounds[1])),  # type: ignore[arg-type]
        category=scene.category,
        background=scene.background,
        camera_distance=(float(dist.min()), float(dist.median()), float(dist.max())),
        scene_type=scene.scene_type.as_json(),
        normalization=scene.normalization.as_json(),
        pose_jumps=walk_jumps(scene.poses[:, :3, :3].double().numpy()),
    )


def format_summary(summary: SceneSummary) -> str:
    """The summary as aligned text lines (no trailing newline)."""
    s = summary
    splits = ", ".join(f"{k} {n}" for k, n in s.views_per_split.items())
    lo, hi = s.bounds
    size = " x ".join(f"{b - a:.3g}" for a, b in zip(lo, hi))
    vary = " (median; varies per view)" if s.intrinsics_vary else ""
    bg = "none (opaque images)" if s.background is None else ", ".join(f"{v:g}" for v in s.background)
    rows = [
        ("format", s.format),
        ("source", s.source),
        ("views", f"{s.n_views} ({splits})"),
        ("test split", s.holdout),
        ("resolution", f"{s.width} x {s.height} (downscale {s.downscale:g})"),
        ("focal", f"fx {s.focal[0]:.2f}, fy {s.focal[1]:.2f} px{vary}"),
        ("principal point", f"cx {s.principal_point[0]:.2f}, cy {s.principal_point[1]:.2f} px{vary}"),
        ("near / far", f"{s.near:.4g} / {s.far:.4g} ({s.near_far_source})"),
        ("bounds", f"min {_vec(lo)}  max {_vec(hi)}  size {size}"),
        ("scene type", f"{s.scene_type['kind']} ({s.scene_type['reason']})"),
        ("category", s.category or "-"),
        ("background", bg),
        ("camera distance", "to bounds centre: min {:.3f}, median {:.3f}, max {:.3f}".format(*s.camera_distance)),
        ("normalisation", describe(Normalization(float(s.normalization["scale"]), tuple(s.normalization["offset"])))),  # type: ignore[arg-type]
        ("pose jumps", folded_walk_note(s.pose_jumps) if s.pose_jumps else "none"),
    ]
    width = max(len(k) for k, _ in rows)
    return "\n".join(f"{k:<{width}}  {v}" for k, v in rows)


def camera_figure(scene: Scene) -> Figure:
    """A 3-D figure of every camera frustum (coloured by split) and the bounds box.

    Two views of the same 3-D scene: an oblique one and one from the side (looking along +y).
    Frusta are drawn ``FRUSTUM_DEPTH_FRACTION`` of the plotted extent deep, with the top image
    edge thicker so upside-down cameras show; axes have equal scales. No global matplotlib state
    is touched (the figure is not registered with pyplot).
    """
    from mpl_toolkits.mplot3d.art3d import Line3DCollection

    poses = scene.poses.double()
    bounds = scene.bounds.double()
    centres = poses[:, :3, 3]
    lo, hi = bounds[0].tolist(), bounds[1].tolist()
    box = torch.tensor([[(hi if (v >> a) & 1 else lo)[a] for a in range(3)] for v in range(8)], dtype=poses.dtype)
    everything = torch.cat([centres, box])
    extent = float((everything.amax(0) - everything.amin(0)).max())
    depth = FRUSTUM_DEPTH_FRACTION * extent
    corners = frustum_corners(poses, scene.intrinsics.double(), scene.height, scene.width, depth)  # (n, 4, 3)
    edges = [(a, b) for a in range(8) for b in range(a + 1, 8) if bin(a ^ b).count("1") == 1]
    box_segments = [[box.tolist()[a], box.tolist()[b]] for a, b in edges]
    points = torch.cat([centres, corners.reshape(-1, 3), box])
    mid = ((points.amax(0) + points.amin(0)) / 2).tolist()
    half = float((points.amax(0) - points.amin(0)).max()) / 2 * 1.05

    fig = Figure(figsize=(12, 6), dpi=100)
    views = ((25.0, -60.0, "oblique view"), (0.0, -90.0, "side view (x right, z up)"))
    for k, (elev, azim, label) in enumerate(views):
        ax = fig.add_subplot(1, 2, k + 1, projection="3d", proj_type="ortho")
        for split, idx in scene.splits.items():
            if not idx:
                continue
            segments, widths = [], []
            for i in idx:
                c, q = centres[i].tolist(), corners[i].tolist()
                for j in range(4):
                    segments.append([c, q[j]])
                    segments.append([q[j], q[(j + 1) % 4]])
                    widths += [0.6, 2.0 if j == 0 else 0.6]
            colour = SPLIT_COLOURS.get(split, "tab:gray")
            ax.add_collection3d(Line3DCollection(segments, colors=colour, linewidths=widths))
            ax.scatter(*centres[list(idx)].T.tolist(), color=colour, s=6, label=f"{split} ({len(idx)})")
        ax.add_collection3d(Line3DCollection(box_segments, colors="black", linewidths=1.2))
        ax.set_xlim(mid[0] - half, mid[0] + half)
        ax.set_ylim(mid[1] - half, mid[1] + half)
        ax.set_zlim(mid[2] - half, mid[2] + half)
        ax.set_box_aspect((1, 1, 1))
        ax.view_init(elev=elev, azim=azim)
        ax.set_xlabel("x")
        ax.set_zlabel("z")
        if elev == 0.0:
            ax.set_yticks([])  # seen edge-on
        else:
            ax.set_ylabel("y")
        ax.set_title(label, fontsize=9)
        if k == 0:
            ax.legend(loc="upper left", fontsize=8)
    fig.suptitle(
        f"{scene.format}: {Path(scene.source).name}, {scene.scene_type.kind} scene ({scene.n_views} views; "
        "bounds in black; thick edge = image top)",
        fontsize=10,
    )
    return fig


def write_camera_plot(scene: Scene, path: str | os.PathLike) -> None:
    """Write :func:`camera_figure` as a PNG, atomically."""
    save_png(camera_figure(scene), path)


def save_png(fig: Figure, path: str | os.PathLike) -> None:
    """Save a figure as PNG through a temporary file renamed into place."""
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png")


def inspect_scene(
    path: str | os.PathLike, options: LoadOptions = LoadOptions(), *, out: str | os.PathLike | None = None
) -> SceneSummary:
    """Load and summarise a scene; with ``out``, write ``out/cameras.png`` and ``out/inspect.json``.

    Everything is loaded and drawn before ``out`` is created, so an error writes nothing.

    Raises:
        SceneError: a bad scene. ConfigError: ``out`` cannot be a folder we write in
            (:func:`~nerfmeta.paths.check_output_folder`) or writing failed.
    """
    out_dir = None if out is None else check_output_folder(out, option="--out", inputs=(path,))
    scene = load_scene_with(path, options)
    summary = summarize_scene(scene)
    if out_dir is not None:
        fig = camera_figure(scene)
        with os_errors_named(out_dir, option="--out"):
            save_png(fig, out_dir / "cameras.png")
            write_json(out_dir / "inspect.json", summary)
    return summary


def _vec(values: tuple[float, ...]) -> str:
    return "[" + ", ".join(f"{v:.3f}" for v in values) + "]"
