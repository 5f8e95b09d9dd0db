"""Poses from photos (issue #16): structure from motion against known poses, into BENCHMARKS.md.

Parts (run under ``flock /work/wt/bench.lock``; each records the load average before it):

* ``synthetic``: the textured cube on a textured ground of ``tests/sfm_scenes.py`` (random
  block texture at two scales), 40 views on a ring (elevation 30 degrees, radius 4.5) at 256 x 192,
  poses removed. ``nerfmeta poses`` with its defaults (``--threads -1``), ``--repeats`` times:
  wall time of the whole command's library call (reading, SIFT, exhaustive matching, mapping,
  undistortion, writing). Views registered, rotation error and camera-centre error after the
  similarity (Umeyama) that maps the SfM centres onto the true ones, as a fraction of the scene
  size (the largest distance between two true camera centres, 9 units). Then two fits of the
  same length (``--iters``, grid, scratch, seed 0) on the SfM scene and on the same photos with
  the true poses (nerfstudio ``transforms.json``): test PSNR of each (every 8th view held out;
  the SfM scene's test images are its undistorted copies).
* ``collection``: a ``nerfmeta make-collection`` chair at 256 px (its 40 training views, poses
  removed): whether the generated objects carry enough texture for SIFT.
* ``beer``: ``../shared/data/real/beer/images`` (71 frames, 720 x 1280) copied without
  ``poses_bounds.npy``; ``nerfmeta poses`` at ``--max-side`` 640, with sequential matching of
  neighbours only (the default), with COLMAP's far pairs too, and with exhaustive matching
  (``--beer-matchers``); views registered, the turn summed over steps of at most 90 degrees, rotation and centre
  errors against the COLMAP poses it ships (``poses_bounds.npy`` converted by nerfmeta's LLFF
  parser's ``llff_to_opengl``): after one similarity over all views, and, since both pose sets put
  a few frames of the walk on the wrong side of the can (consecutive frames more than 90 degrees
  apart: a symmetric can on a repeating tile grid), per step (the rotation from each frame to the
  next, no alignment needed) and after a similarity over the longest run of frames with no such
  jump in either set.

Usage::

    flock /work/wt/bench.lock .venv/bin/python scripts/bench_poses.py synthetic collection beer --work NEW_FOLDER

``--work`` (default ``/tmp/bench_poses``) must be absent or empty: the script refuses anything else
and deletes nothing.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))

import sfm_scenes  # noqa: E402

from nerfmeta.data.llff import llff_to_opengl  # noqa: E402
from nerfmeta.data.sfm import SfmConfig, compute_poses, rotation_steps_deg  # noqa: E402
from benchlib.workdir import work_folder_error  # noqa: E402

BEER = ROOT.parent / "shared" / "data" / "real" / "beer"


def load() -> str:
    one, five, fifteen = os.getloadavg()
    return f"{one:.2f}/{five:.2f}/{fifteen:.2f}"


def pose_report(estimated: np.ndarray, true: np.ndarray) -> dict:
    """Rotation (degrees) and centre errors (fraction of the true cameras' extent) after a similarity."""
    rot, centre = sfm_scenes.pose_errors(estimated, true)
    centres = true[:, :3, 3]
    extent = float(np.max(np.linalg.norm(centres[:, None] - centres[None], axis=-1)))
    return {"rot_median_deg": float(np.median(rot)), "rot_max_deg": float(rot.max()),
            "centre_median_pct": float(np.median(centre) / extent * 100), "centre_max_pct": float(centre.max() / extent * 100),
            "extent": extent}


def sfm_poses(scene: Path) -> dict[str, np.ndarray]:
    doc = json.loads((scene / "transforms.json").read_text())
    return {Path(f["file_path"]).name: np.array(f["transform_matrix"]) for f in doc["frames"]}


def fit(scene: Path, out: Path, iters: int) -> dict:
    cmd = [sys.executable, "-m", "nerfmeta", "fit", str(scene), "--out", str(out), "--init", "scratch", "--iters", str(iters),
           "--renders", "0", "--no-eval-ssim", "--eval-every", "0"]
    subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, env={**os.environ, "NERFMETA_ZOO": "none"})
    summary = json.loads((out / "summary.json").read_text())
    return {"test_psnr": summary["test_psnr"], "time_s": summary["time_s"], "iters": summary["iters"]}


def synthetic(work: Path, repeats: int, iters: int) -> dict:
    true = sfm_scenes.ring_poses(40)
    images = sfm_scenes.render(true, 0.8 * 256, 192, 256)
    photos = work / "synthetic" / "photos"
    sfm_scenes.write_photos(photos, images)
    sfm_scenes.write_blender(work / "synthetic" / "true", images, true, 0.8 * 256)
    runs = []
    for k in range(repeats):
        out = work / "synthetic" / f"sfm{k}"
        before = load()
        t0 = time.perf_counter()
        result = compute_poses(photos, out, SfmConfig())
        wall = time.perf_counter() - t0
        poses = sfm_poses(out)
        names = sorted(poses)
        idx = [int(n[5:8]) for n in names]
        runs.append({"wall_s": wall, "load": before, "registered": len(result.registered), "phases": result.seconds,
                     **pose_report(np.stack([poses[n] for n in names]), true[idx])})
    report = {"views": 40, "size": "256x192", "runs": runs, "median_wall_s": statistics.median(r["wall_s"] for r in runs)}
    if iters:
        report["fit_load"] = load()
        report["fit_sfm"] = fit(work / "synthetic" / "sfm0", work / "synthetic" / "fit_sfm", iters)
        report["fit_true"] = fit(work / "synthetic" / "true", work / "synthetic" / "fit_true", iters)
    return report


def collection(work: Path) -> dict:
    coll = work / "collection"
    subprocess.run([sys.executable, "-m", "nerfmeta", "make-collection", str(coll), "--categories", "chair",
                    "--scenes-per-category", "1", "--views", "40", "--test-views", "1", "--resolution", "256",
                    "--val-fraction", "0", "--test-fraction", "0", "--workers", "1"], check=True, stdout=subprocess.DEVNULL)
    scene = next(p.parent for p in coll.rglob("transforms_train.json"))
    photos = work / "collection_photos"
    shutil.copytree(scene / "train", photos)
    out = work / "collection_sfm"
    before = load()
    t0 = time.perf_counter()
    try:
        result = compute_poses(photos, out, SfmConfig(min_registered=0.01))
        outcome = {"registered": len(result.registered), "points": result.points}
    except Exception as err:  # the measurement is whether it works: record the one line
        outcome = {"registered": 0, "error": str(err)}
    return {"views": 40, "load": before, "wall_s": time.perf_counter() - t0, **outcome}


def step_rotations_deg(poses: np.ndarray) -> np.ndarray:
    """(n - 1,) rotation angle between consecutive cameras (a video's frames turn a few degrees each)."""
    return rotation_steps_deg(poses[:, :3, :3])


def relative_rotation_errors_deg(estimated: np.ndarray, true: np.ndarray) -> np.ndarray:
    """(n - 1,) angle between the estimated and the true rotation from each frame to the next (no alignment needed)."""
    rel_e = np.einsum("nji,njk->nik", estimated[:-1, :3, :3], estimated[1:, :3, :3])
    rel_t = np.einsum("nji,njk->nik", true[:-1, :3, :3], true[1:, :3, :3])
    diff = np.einsum("nji,njk->nik", rel_e, rel_t)
    return np.degrees(np.arccos(np.clip((np.trace(diff, axis1=1, axis2=2) - 1) / 2, -1, 1)))


def segments(*pose_sets: np.ndarray, jump_deg: float = 90.0) -> list[tuple[int, int]]:
    """``[start, end)`` runs of consecutive frames with no step above ``jump_deg`` in any of the pose sets."""
    bad = np.zeros(len(pose_sets[0]) - 1, bool)
    for poses in pose_sets:
        bad |= step_rotations_deg(poses) > jump_deg
    cuts = [0, *(int(i) + 1 for i in np.flatnonzero(bad)), len(pose_sets[0])]
    return [(a, b) for a, b in zip(cuts, cuts[1:]) if b > a]


def shipped_beer_poses() -> dict[str, np.ndarray]:
    """Beer's COLMAP poses by image name, OpenGL camera-to-world (``poses_bounds.npy`` rows follow the sorted ``images/``)."""
    rows = np.load(BEER / "poses_bounds.npy")
    poses = llff_to_opengl(rows[:, :15].reshape(-1, 3, 5)[:, :, :4])
    return dict(zip(sorted(p.name for p in (BEER / "images").iterdir()), poses))


BEER_MATCHERS = {
    "sequential": {"matcher": "sequential"},  # neighbours only: each frame with the next 10
    "sequential-far": {"matcher": "sequential", "far_pairs": True},  # the ones 1, 2, 4, ... 512 later (COLMAP's default)
    "exhaustive": {"matcher": "exhaustive"},
}
"""The ``--beer-matchers`` choices: :class:`SfmConfig` fields."""


def beer(work: Path, max_side: int, matcher: str) -> dict:
    photos = work / "beer_photos"
    if not photos.is_dir():  # one copy for every matcher of this run
        shutil.copytree(BEER / "images", photos)
    out = work / f"beer_sfm_{max_side}_{matcher}"
    before = load()
    t0 = time.perf_counter()
    result = compute_poses(photos, out, SfmConfig(max_side=max_side, min_registered=0.5, **BEER_MATCHERS[matcher]))
    wall = time.perf_counter() - t0
    true = shipped_beer_poses()
    poses = sfm_poses(out)
    names = sorted(set(poses) & set(true))
    est, ref = np.stack([poses[n] for n in names]), np.stack([true[n] for n in names])
    runs = segments(est, ref)
    longest = max(runs, key=lambda r: r[1] - r[0])
    rel = relative_rotation_errors_deg(est, ref)
    return {"views": len(list(photos.iterdir())), "registered": len(result.registered), "max_side": max_side,
            "matcher": matcher, "load": before, "wall_s": wall, "phases": result.seconds,
            "unregistered": list(result.unregistered), "global": pose_report(est, ref),
            "jumps_sfm": [names[i + 1] for i in np.flatnonzero(step_rotations_deg(est) > 90)],
            "jumps_shipped": [names[i + 1] for i in np.flatnonzero(step_rotations_deg(ref) > 90)],
            "turned_sfm_deg": float(step_rotations_deg(est)[step_rotations_deg(est) <= 90].sum()),
            "turned_shipped_deg": float(step_rotations_deg(ref)[step_rotations_deg(ref) <= 90].sum()),
            "step_rotation_error_median_deg": float(np.median(rel)), "step_rotation_error_p90_deg": float(np.percentile(rel, 90)),
            "longest_segment": [names[longest[0]], names[longest[1] - 1]],
            "longest_segment_errors": pose_report(est[longest[0]:longest[1]], ref[longest[0]:longest[1]])}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("parts", nargs="+", choices=("synthetic", "collection", "beer"))
    parser.add_argument("--work", type=Path, default=Path("/tmp/bench_poses"),
                        help="scratch folder, absent or empty (nothing in it is deleted)")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--iters", type=int, default=400, help="fit length for the SfM-vs-true comparison (0: none)")
    parser.add_argument("--beer-max-side", type=int, default=640)
    parser.add_argument("--beer-matchers", default="sequential,sequential-far,exhaustive",
                        help=f"comma-separated, of: {', '.join(BEER_MATCHERS)}")
    args = parser.parse_args()
    refusal = work_folder_error(args.work)
    if refusal:
        print(refusal, file=sys.stderr)
        return 2
    args.work.mkdir(parents=True, exist_ok=True)
    results = {}
    for part in args.parts:
        if part == "synthetic":
            results[part] = synthetic(args.work, args.repeats, args.iters)
        elif part == "collection":
            results[part] = collection(args.work)
        else:
            results[part] = [beer(args.work, args.beer_max_side, m) for m in args.beer_matchers.split(",")]
        print(json.dumps({part: results[part]}, indent=1), flush=True)
    (args.work / "results.json").write_text(json.dumps(results, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
