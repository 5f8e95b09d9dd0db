"""How often COLMAP's mapping bends a walk, and whether ``match_agreement`` tells (issue #16), into BENCHMARKS.md.

COLMAP's incremental mapping is not repeatable on several threads. This matches the photos once as
``nerfmeta poses``'s ``auto`` matcher does (every pair, then the neighbours only on the same features),
maps the neighbours' matches ``--draws`` times (seeds 0, 1, ...) with the incremental mapper and
``--global-draws`` times with the global one, and prints for each draw the photos
registered, the share of every pair's verified matches its poses explain
(:func:`nerfmeta.data.sfm.match_agreement`) and how far its worst photo turns from the first draw's
after the best common rotation (a bent walk turns part of the photos by the bend's angle).

Usage::

    .venv/bin/python scripts/bench_map_draws.py ../shared/data/real/beer/images --work /tmp/draws [--draws 20]
"""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from nerfmeta.data.images import list_photos  # noqa: E402
from nerfmeta.data.sfm import (  # noqa: E402
    SfmConfig,
    check_photos,
    prepared_names,
    map_matches,
    match_agreement,
    prepare_photo,
    prepared_size,
    read_verified_matches,
    reconstruct,
)
from benchlib.workdir import work_folder_error  # noqa: E402


def worst_turn_deg(rotations: np.ndarray, reference: np.ndarray) -> float:
    """Largest angle (degrees) between ``rotations`` (n, 3, 3) and ``reference`` after the best common rotation."""
    relative = np.einsum("nij,nkj->nik", rotations, reference)
    u, _, vt = np.linalg.svd(relative.sum(0))
    common = u @ np.diag([1.0, 1.0, np.sign(np.linalg.det(u @ vt))]) @ vt
    cos = (np.einsum("ij,nij->n", common, relative) - 1) / 2
    return float(np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))).max())


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("photos", type=Path)
    parser.add_argument("--work", type=Path, required=True, help="scratch folder, absent or empty")
    parser.add_argument("--draws", type=int, default=20, help="incremental mappings (seeds 0, 1, ...)")
    parser.add_argument("--global-draws", type=int, default=1, help="global (GLOMAP) mappings after them")
    parser.add_argument("--max-side", type=int, default=SfmConfig().max_side)
    args = parser.parse_args()
    config = SfmConfig(max_side=args.max_side)
    refusal = work_folder_error(args.work)
    if refusal:
        print(refusal, file=sys.stderr)
        return 2
    paths = list_photos(args.photos)
    (height, width), turned = check_photos(paths, args.photos)
    photos = args.work / "photos"
    photos.mkdir(parents=True)
    scene_names = prepared_names(paths)
    names = [scene_names[p.name] for p in paths]
    for path in paths:
        prepare_photo(path, photos / scene_names[path.name], prepared_size(height, width, config.max_side),
                      turn=path.name in turned)
    quiet, seconds = (lambda *_: None), {}
    every, neighbours = args.work / "exhaustive", args.work / "sequential"
    every.mkdir()
    neighbours.mkdir()
    reconstruct(photos, names, every, replace(config, matcher="exhaustive"), quiet, seconds)
    reconstruct(photos, names, neighbours, replace(config, matcher="sequential"), quiet, seconds,
                features=every / "database.db")
    print(f"{len(names)} photos at {prepared_size(height, width, config.max_side)}; features and matching "
          f"{seconds['features'] + seconds['matching']:.1f} s")
    matches = read_verified_matches(every / "database.db")
    reference = None
    for seed, mapper in [(seed, "incremental") for seed in range(args.draws)] + [(0, "global")] * args.global_draws:
        t0 = time.perf_counter()
        model = map_matches(neighbours / "database.db", photos, len(names), args.work / f"{mapper}-{seed}-{t0:.0f}", config,
                            quiet, {}, seed=seed, mapper=mapper)
        posed = {image.name: image for image in model.images.values() if image.has_pose} if model else {}
        common = [n for n in names if n in posed]
        rotations = np.array([np.asarray(posed[n].cam_from_world().rotation.matrix()) for n in common])
        if reference is None:
            reference = dict(zip(common, rotations))
        shared = [k for k, n in enumerate(common) if n in reference]
        turn = worst_turn_deg(rotations[shared], np.array([reference[common[k]] for k in shared])) if shared else float("nan")
        print(f"{mapper} seed {seed}: {len(posed)}/{len(names)} registered, agreement {match_agreement(model, matches):.4f}, "
              f"worst photo {turn:.2f} deg from seed 0's, {time.perf_counter() - t0:.1f} s", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
