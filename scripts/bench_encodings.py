"""The surface study replayed: the SDF backbone with five input encodings on generated scenes (and lego).

For every scene of a generated collection (one per category) and every encoding, one
``python -m nerfmeta fit SCENE --backbone sdf --set encoding=E --time-budget BUDGET`` in its own
process (so ``peak_rss_mb`` is its own), one torch thread each, ``--workers`` at a time (default 1: back to
back). The ground truth of every scene is sampled first; with ``--lock FILE`` the fits run holding that
lock (``flock``: one benchmark at a time across a shared machine, acquired once, as the lock is not fair
and taking it per fit could starve). Scenes are the outer loop and encodings the inner one, so the
machine's load hits every encoding alike. After all the fits, outside the timed part and with nothing
else running, each run is meshed at ``--resolution`` and compared with the scene's exact SDF
(``nerfmeta.geometry``: Chamfer as % of the ground truth's bounding-box diagonal, F-score at 1 %
of it, normal consistency), and the mean ``|grad f|`` of the SDF is taken at points sampled on the
true surface. Lego (``--lego``) gives PSNR/SSIM/LPIPS only (no ground-truth geometry). Writes
``OUT/results.json``, ``OUT/table.md`` and ``OUT/meshes.png`` (each scene's meshes side by side,
faces coloured by their distance to the true surface).

Usage::

    .venv/bin/python scripts/bench_encodings.py COLLECTION --out DIR [--budget 60] [--lego PATH] [--workers 2]
        [--encodings pe,fourier,hash,nffb,stylemod-nffb] [--batch-rays 512] [--set KEY=VALUE ...] [--lock FILE]
"""

from __future__ import annotations

import argparse
import fcntl
import json
import os
import statistics
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import nerfmeta  # noqa: E402,F401 - before torch, which then spins its OpenMP workers briefly (nerfmeta/__init__.py)
import torch  # noqa: E402

from nerfmeta.collection.generate import load_collection  # noqa: E402
from nerfmeta.geometry.metrics import GeometryConfig  # noqa: E402
from nerfmeta.geometry.load import load_run_model  # noqa: E402
from nerfmeta.geometry.runs import evaluate_mesh, mesh_in_file_frame  # noqa: E402
from nerfmeta.geometry.truth import sample_sdf_surface, scene_sdf_of  # noqa: E402

ENCODINGS = ("pe", "fourier", "hash", "nffb", "stylemod-nffb")


def fit(scene: Path, out: Path, encoding: str, args: argparse.Namespace, extra: list[str]) -> dict:
    """One time-budgeted fit in its own process; its summary plus the load average when it started."""
    cmd = [sys.executable, "-m", "nerfmeta", "fit", str(scene), "--out", str(out), "--init", "scratch", "--backbone", "sdf",
           "--time-budget", f"{args.budget:g}", "--iters", str(args.iters), "--batch-rays", str(args.batch_rays),
           "--eval-every", "0", "--checkpoint-every", "0", "--eval-views", str(args.eval_views), "--renders", "1",
           "--set", f"encoding={encoding}", *extra]
    for item in args.set:
        cmd += ["--set", item]
    env = {**os.environ, "OMP_NUM_THREADS": "1", "NERFMETA_ZOO": "none"}
    load = Path("/proc/loadavg").read_text().split()[:3]
    t0 = time.time()
    done = subprocess.run(cmd, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    if done.returncode != 0:  # a failed fit is a finding of the study: recorded, and the study goes on
        lines = [line for line in done.stderr.replace("\r", "\n").splitlines() if line.strip()]
        return {"error": lines[-1] if lines else f"exit status {done.returncode}", "load_average": load}
    summary = json.loads((out / "summary.json").read_text())
    summary["load_average"] = load
    summary["wall_s"] = round(time.time() - t0, 1)
    return summary


def grad_near_surface(model, scene, points: np.ndarray) -> float:
    """Mean |grad f| of an SDF model at file-frame surface points (mapped to the loaded frame)."""
    loaded = scene.normalization.apply_points(torch.as_tensor(points, dtype=torch.float32))
    grads = []
    for chunk in torch.split(loaded, 8192):
        with torch.no_grad():
            grads.append(model.evaluate(model.to_box(chunk)).grad.norm(dim=-1))
    return float(torch.cat(grads).mean())


def geometry_row(run: Path, scene_dir: Path, gt, config: GeometryConfig) -> tuple[dict, object]:
    model, scene = load_run_model(run)
    mesh = mesh_in_file_frame(model, scene, config.resolution, colors=False)
    m = evaluate_mesh(mesh, gt, config)
    return {"chamfer_pct": m.chamfer_pct_diagonal, "fscore": m.fscore, "normal_consistency": m.normal_consistency,
            "grad_norm": grad_near_surface(model, scene, gt.points[:20000])}, mesh


def distance_colours(mesh, sdf, clip: float) -> np.ndarray:
    """(F, 4) RGBA per face from |exact SDF| at its centroid, 0 (blue) .. clip (red)."""
    import matplotlib

    centres = torch.as_tensor(mesh.vertices[mesh.faces].mean(1), dtype=torch.float64)
    d = sdf(centres).abs().numpy()
    return matplotlib.colormaps["turbo"](np.clip(d / clip, 0, 1))


def picture(rows: list[tuple[str, list[tuple[str, object]]]], sdfs: dict, diagonals: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from mpl_toolkits.mplot3d.art3d import Poly3DCollection

    n_rows, n_cols = len(rows), max(len(r[1]) for r in rows)
    fig = plt.figure(figsize=(3 * n_cols, 3 * n_rows))
    for i, (scene_name, meshes) in enumerate(rows):
        for j, (label, mesh) in enumerate(meshes):
            ax = fig.add_subplot(n_rows, n_cols, i * n_cols + j + 1, projection="3d")
            clip = 0.02 * diagonals[scene_name]
            coll = Poly3DCollection(mesh.vertices[mesh.faces], facecolors=distance_colours(mesh, sdfs[scene_name], clip),
                                    edgecolor="none")
            ax.add_collection3d(coll)
            lo, hi = mesh.vertices.min(0), mesh.vertices.max(0)
            c, r = 0.5 * (lo + hi), 0.5 * float((hi - lo).max())
            ax.set_xlim(c[0] - r, c[0] + r), ax.set_ylim(c[1] - r, c[1] + r), ax.set_zlim(c[2] - r, c[2] + r)
            ax.view_init(elev=20, azim=35)
            ax.set_axis_off()
            ax.set_title(f"{scene_name}\n{label}", fontsize=8)
    fig.suptitle("meshes coloured by distance to the exact surface: blue 0 .. red >= 2% of the bbox diagonal", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=80)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("collection", type=Path)
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--budget", type=float, default=60.0, help="optimisation seconds per fit")
    parser.add_argument("--encodings", default=",".join(ENCODINGS))
    parser.add_argument("--lego", type=Path, default=None, help="lego folder for PSNR/SSIM (fitted at --lego-downscale)")
    parser.add_argument("--lego-downscale", type=float, default=8.0)
    parser.add_argument("--batch-rays", type=int, default=512)
    parser.add_argument("--eval-views", type=int, default=4)
    parser.add_argument("--resolution", type=int, default=128, help="marching-cubes corners per axis")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE")
    parser.add_argument("--iters", type=int, default=1000000, help="iterations per fit (the same for every encoding)")
    parser.add_argument("--workers", type=int, default=1, help="fits at a time (one torch thread each)")
    parser.add_argument("--lock", type=Path, default=None, metavar="FILE",
                        help="hold this flock file while fitting (a machine shared with other benchmarks)")
    parser.add_argument("--no-lock", dest="lock", action="store_const", const=None,
                        help="take no lock (the default; kept for the commands recorded in BENCHMARKS.md)")
    args = parser.parse_args(argv)
    if args.workers < 1:
        parser.error(f"--workers must be at least 1, got {args.workers}")
    encodings = args.encodings.split(",")
    args.out.mkdir(parents=True, exist_ok=False)
    collection = load_collection(args.collection)
    config = GeometryConfig(resolution=args.resolution, n_points=100000)
    results, sdfs, diagonals, gts = [], {}, {}, {}
    for record in collection.scenes:
        sdf, box = scene_sdf_of(collection.scene_path(record))
        gts[record.name] = sample_sdf_surface(sdf, box, config.n_points, resolution=160, seed=1)
        sdfs[record.name], diagonals[record.name] = sdf, float(np.linalg.norm(gts[record.name].points.max(0) - gts[record.name].points.min(0)))
    jobs = [(record.name, record.category, collection.scene_path(record), enc, []) for record in collection.scenes
            for enc in encodings]
    if args.lego is not None:
        jobs += [("lego", "lego", args.lego, enc, ["--downscale", f"{args.lego_downscale:g}"]) for enc in encodings]

    def one(job: tuple) -> dict:
        name, _, scene_dir, enc, extra = job
        run = args.out / name / enc
        run.parent.mkdir(parents=True, exist_ok=True)
        summary = fit(scene_dir, run, enc, args, extra)
        if "error" in summary:
            print(f"{name} {enc}: FAILED: {summary['error']}", flush=True)
        else:
            print(f"{name} {enc}: {summary['iters']} iterations, {summary['test_psnr']:.2f} dB", flush=True)
        return summary

    with open(args.lock, "a") if args.lock is not None else open(os.devnull) as lock:
        if args.lock is not None:
            print("waiting for", args.lock, flush=True)
            fcntl.flock(lock, fcntl.LOCK_EX)
            print("lock taken at", time.strftime("%H:%M:%S"), flush=True)
        with ThreadPoolExecutor(args.workers) as pool:
            summaries = list(pool.map(one, jobs))
    # the geometry after every fit has ended, so no timed fit shares the machine with it
    meshes: dict[str, list] = {}
    for (name, category, scene_dir, enc, _), summary in zip(jobs, summaries):
        if "error" in summary:
            results.append({"scene": name, "encoding": enc, "error": summary["error"], "load": summary["load_average"]})
            print(json.dumps(results[-1]), flush=True)
            continue
        row = {"scene": name, "category": category, "encoding": enc, "psnr": summary["test_psnr"],
               "ssim": summary["test_ssim"], "lpips": summary.get("test_lpips"), "iters": summary["iters"],
               "time_s": summary["time_s"], "peak_rss_mb": summary["peak_rss_mb"], "load": summary["load_average"]}
        if name != "lego":
            geo, mesh = geometry_row(args.out / name / enc, scene_dir, gts[name], config)
            row.update(geo)
            meshes.setdefault(name, []).append((f"{enc}: {geo['chamfer_pct']:.2f}%", mesh))
        print(json.dumps(row), flush=True)
        results.append(row)
    picture_rows = list(meshes.items())
    (args.out / "results.json").write_text(json.dumps(results, indent=1))
    (args.out / "table.md").write_text(table(results, encodings))
    if picture_rows:
        picture(picture_rows, sdfs, diagonals, args.out / "meshes.png")
    print(table(results, encodings))
    return 0


def table(results: list[dict], encodings: list[str]) -> str:
    """Median over the generated scenes per encoding, and lego's PSNR/SSIM."""
    lines = ["| encoding | Chamfer (% diag), median [min..max] | F-score @1% | normal cons. | mean abs grad f at surface | PSNR (dB) | SSIM | "
             "LPIPS | iters | optimisation s | peak RSS (MB) | lego PSNR / SSIM / LPIPS (iters) |",
             "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
    failed = [r for r in results if "error" in r]
    results = [r for r in results if "error" not in r]
    for enc in encodings:
        rows = [r for r in results if r["encoding"] == enc and r["scene"] != "lego"]
        lego = [r for r in results if r["encoding"] == enc and r["scene"] == "lego"]
        if not rows:
            continue

        def med(key: str, digits: int = 2) -> str:
            values = [r[key] for r in rows if r.get(key) is not None]
            return f"{statistics.median(values):.{digits}f}" if values else "-"

        def fmt(value: float | None, digits: int) -> str:
            return "-" if value is None else f"{value:.{digits}f}"

        cham = [r["chamfer_pct"] for r in rows]
        lego_txt = (f"{lego[0]['psnr']:.2f} / {lego[0]['ssim']:.3f} / {fmt(lego[0].get('lpips'), 3)} ({lego[0]['iters']})"
                    if lego else "-")
        lines.append(f"| {enc} | {statistics.median(cham):.2f} [{min(cham):.2f}..{max(cham):.2f}] | {med('fscore', 3)} | "
                     f"{med('normal_consistency', 3)} | {med('grad_norm', 3)} | {med('psnr')} | {med('ssim', 3)} | {med('lpips', 3)} | "
                     f"{med('iters', 0)} | {med('time_s', 0)} | {med('peak_rss_mb', 0)} | {lego_txt} |")
    if failed:
        lines += [""] + [f"Failed: {r['scene']} with {r['encoding']}: {r['error']}" for r in failed]
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    raise SystemExit(main())
