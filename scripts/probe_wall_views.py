"""How much do a generated mug's training views say about where its inner wall is?

Session 45's probe for #19's thick inner walls (BENCHMARKS.md, *Surfaces: carving concavities*, section 22). For each
``SEED:TEXTURE`` it builds the mug of ``make-collection --categories mug --scenes-per-category 1 --views 40
--test-views 8 --resolution 128 --seed SEED``, with its body's and handle's texture as generated (``keep``), ``plain``
or ``checker`` (a 3-D checkerboard of 5.65 cycles per shape unit, the seed-7 mug's, its second colour the texture's
own or, for a plain mug, a contrasting one), and a copy whose body shell is thickened towards the cavity by each
``--thicker`` (% of the object's bounding-box diagonal): the revolved profile moved half of it towards the cavity and
its half-thickness grown by as much, so the outside and the rim's top stay where they were. It prints the Chamfer
distance between the two exact surfaces and the PSNR between their 40 training views (RGB on white): the lower the
PSNR, the more the views pin the wall down. ``--write DIR`` also writes each variant as a one-scene collection
(``DIR/SEED_TEXTURE``, as ``make-collection`` would), to fit and score with ``nerfmeta fit`` and ``eval-geometry``.

Usage::

    .venv/bin/python scripts/probe_wall_views.py 53:keep 53:checker 43:keep [--thicker 1.0] [--write DIR]
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import nerfmeta  # noqa: E402,F401 - before torch, which then spins its OpenMP workers briefly (nerfmeta/__init__.py)
import torch  # noqa: E402

from nerfmeta.collection.generate import (CollectionConfig, SceneRecord, camera_poses, collection_document,  # noqa: E402
                                          plan_collection, write_scene)
from nerfmeta.collection.render import render_views  # noqa: E402
from nerfmeta.collection.shapes import Revolution, Shape  # noqa: E402
from nerfmeta.geometry.metrics import compare_surfaces  # noqa: E402
from nerfmeta.geometry.truth import sample_sdf_surface  # noqa: E402
from nerfmeta.io import write_json  # noqa: E402
from nerfmeta.runfolder import run_folder  # noqa: E402

CHECKER_FREQUENCY = 5.65
"""Cycles per shape unit of the checkerboard put on a mug (the seed-7 mug's own, whose wall fits landed best)."""


def retextured(shape: Shape, texture: str) -> Shape:
    """``shape`` with every part's texture as it was (``keep``), ``plain`` or ``checker``."""
    if texture == "keep":
        return shape
    parts = []
    for part in shape.parts:
        m = part.material
        if texture == "plain":
            m = dataclasses.replace(m, texture="plain")
        else:
            second = m.color2 if m.texture != "plain" else tuple(round(1.0 - 0.8 * c, 4) for c in m.color)
            m = dataclasses.replace(m, texture="checker", color2=second, frequency=CHECKER_FREQUENCY, phase=0.3)
        parts.append(dataclasses.replace(part, material=m))
    return dataclasses.replace(shape, parts=tuple(parts))


def thickened_inwards(shape: Shape, delta: float) -> Shape:
    """``shape`` with its ``body`` shell (a :class:`Revolution`) ``delta`` shape units thicker towards the cavity.

    The profile (r, z) runs from the axis along the bottom and up the side, so the cavity lies to the left of its
    direction of travel: each segment moves ``delta / 2`` along its left normal (inner vertices mitred) and the
    half-thickness grows by ``delta / 2``, which leaves the far side of the shell where it was. The last vertex also
    moves ``delta / 2`` down, so the rim's top stays at its height; the first stays on the axis."""
    parts = []
    for part in shape.parts:
        if part.name == "body":
            prof = np.asarray(part.primitive.profile, dtype=float)
            seg = np.diff(prof, axis=0)
            seg /= np.linalg.norm(seg, axis=1, keepdims=True)
            left = np.stack([-seg[:, 1], seg[:, 0]], axis=1)
            # a mitred offset: an inner vertex moves along (n1 + n2) / (1 + n1.n2), which puts both of its segments
            # exactly delta / 2 further in
            mitre = (left[:-1] + left[1:]) / (1.0 + (left[:-1] * left[1:]).sum(axis=1, keepdims=True))
            moved = prof + 0.5 * delta * np.concatenate([left[:1], mitre, left[-1:]])
            moved[-1, 1] -= 0.5 * delta
            moved[0, 0] = 0.0
            primitive = Revolution(tuple((float(r), float(z)) for r, z in moved), part.primitive.half_thickness + 0.5 * delta)
            part = dataclasses.replace(part, primitive=primitive)
        parts.append(part)
    return dataclasses.replace(shape, parts=tuple(parts))


def training_views(record: SceneRecord, config: CollectionConfig) -> torch.Tensor:
    """(V, H, W, 3) the record's training views, composited on white."""
    poses, _ = camera_poses(config, record.azimuth)
    aabb = torch.as_tensor(record.aabb, dtype=torch.float32)
    rgba = render_views(record.sdf, record.shape.albedo, poses, config.focal, config.resolution, config.resolution, aabb,
                        config.render)
    return rgba[..., :3] * rgba[..., 3:] + (1.0 - rgba[..., 3:])


def mug_record(seed: int, texture: str) -> tuple[SceneRecord, CollectionConfig]:
    """The seed's mug (``make-collection``'s plan) with its texture set, and the collection's config."""
    config = CollectionConfig(categories=("mug",), scenes_per_category=1, views=40, test_views=8, resolution=128, seed=seed)
    record = plan_collection(config)[0]
    return dataclasses.replace(record, shape=retextured(record.shape, texture)), config


def write_collection(record: SceneRecord, config: CollectionConfig, out: Path) -> None:
    """``record`` as a one-scene collection in ``out``, as ``make-collection`` writes one: built aside and swapped in
    when complete, and never over a folder the project did not write (:func:`~nerfmeta.runfolder.run_folder`)."""
    with run_folder(out, "collection", aside=True) as run:
        write_scene(record, config, run.dir)
        write_json(run.dir / "collection.json", collection_document(config, [record]))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("variants", nargs="+", metavar="SEED:TEXTURE", help="TEXTURE: keep, plain or checker")
    parser.add_argument("--thicker", default="1.0", help="comma-separated wall thickenings, %% of the diagonal")
    parser.add_argument("--points", type=int, default=200_000, help="surface samples a side for the Chamfer distance")
    parser.add_argument("--write", type=Path, default=None, metavar="DIR", help="write each variant's collection here")
    args = parser.parse_args(argv)
    for spec in args.variants:
        seed_text, _, texture = spec.partition(":")
        if texture not in ("keep", "plain", "checker") or not seed_text.isdigit():
            parser.error(f"{spec!r}: expected SEED:TEXTURE with TEXTURE keep, plain or checker")
        record, config = mug_record(int(seed_text), texture)
        if args.write is not None:
            write_collection(record, config, args.write / f"{seed_text}_{texture}")
        truth = sample_sdf_surface(record.sdf, record.aabb, args.points)
        diagonal = float(np.linalg.norm(truth.points.max(0) - truth.points.min(0)))
        base = training_views(record, config)
        body = next(p.material.texture for p in record.shape.parts if p.name == "body")
        for pct in (float(t) for t in args.thicker.split(",")):
            thick = dataclasses.replace(record, shape=thickened_inwards(record.shape, pct / 100 * diagonal / record.shape.scale))
            other = sample_sdf_surface(thick.sdf, thick.aabb, args.points, seed=1)
            chamfer = compare_surfaces(other.points, truth.points).chamfer_pct_diagonal
            mse = ((training_views(thick, config) - base) ** 2).mean(dim=(1, 2, 3))
            print(f"seed {seed_text} body {body:8s} wall {pct:.2f} % of the diagonal thicker inwards: Chamfer {chamfer:.3f} %, "
                  f"training views {float(-10 * torch.log10(mse.mean())):.2f} dB apart "
                  f"(closest view {float(-10 * torch.log10(mse.min())):.2f}, farthest {float(-10 * torch.log10(mse.max())):.2f})",
                  flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
