"""Distributed meta-training: ``torchrun`` with 2 CPU processes (gloo) equals a 1-process run."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from nerfmeta.cli import main
from nerfmeta.collection.generate import CollectionConfig, generate_collection
from nerfmeta.collection.render import RenderConfig
from nerfmeta.io import load_tensors

REPO = Path(__file__).resolve().parents[1]
ARGS = ["--algo", "maml", "--meta-steps", "3", "--meta-batch", "4", "--support-rays", "48", "--query-rays", "48",
        "--inner-steps", "2", "--eval-tasks", "0", "--checkpoint-every", "2",
        "--set", "depth=2", "--set", "width=16", "--set", "skips=[]", "--set", "n_samples=8", "--set", "pos_freqs=2"]

FAST_RENDER = RenderConfig(supersample=1, max_steps=48)  # the images only need to differ per scene


def torchrun_env() -> dict[str, str]:
    """This repository importable, one thread a process, and no rank variables of an outer run."""
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")]),
           "OMP_NUM_THREADS": "1"}
    env.pop("RANK", None)
    env.pop("WORLD_SIZE", None)
    return env


@pytest.mark.slow
def test_two_processes_learn_the_same_parameters_as_one(tmp_path: Path):
    if not torch.distributed.is_available():
        pytest.skip("torch.distributed is not available in this build of torch")
    coll = tmp_path / "coll"
    generate_collection(CollectionConfig(categories=("mug", "vase"), scenes_per_category=3, views=3, test_views=1,
                                         resolution=12, val_fraction=0.0, test_fraction=0.0, render=FAST_RENDER), coll)
    env = torchrun_env()
    one, two = tmp_path / "one", tmp_path / "two"
    double = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node", "2",
              "-m", "nerfmeta", "meta-train", str(coll), "--out", str(two), *ARGS]
    launched = subprocess.Popen(double, cwd=REPO, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        assert main(["meta-train", str(coll), "--out", str(one), *ARGS]) == 0
    finally:
        torch.set_num_threads(threads)
    _, err = launched.communicate(timeout=120)
    assert launched.returncode == 0, err[-3000:]
    a, b = load_tensors(one / "model.safetensors"), load_tensors(two / "model.safetensors")
    assert a.keys() == b.keys()
    worst = 0.0
    for name in a:
        diff = float((a[name] - b[name]).abs().max())
        worst = max(worst, diff / max(float(a[name].abs().max()), 1e-12))
    print(f"1 vs 2 processes: worst relative parameter difference {worst:.3e}")
    assert worst <= 1e-6
    summary = json.loads((two / "summary.json").read_text())
    assert summary["world_size"] == 2
    tasks = lambda run: [json.loads(line)["tasks"] for line in (run / "metrics.jsonl").read_text().splitlines()]  # noqa: E731
    assert tasks(one) == tasks(two) and len(tasks(one)) == 3
    # the parameters moved: the comparison is not between two untouched initialisations
    from pretrain.meta_run import build_meta_model, saved_config

    start = build_meta_model(saved_config(one), torch.device("cpu")).state_dict()
    moved = max(float((a[name] - start[name]).abs().max()) for name in a)
    assert moved > 1e3 * worst * max(float(v.abs().max()) for v in a.values())


WORKER = """
import os, sys
import torch
from pretrain.meta_dist import distributed_from_env

def threads():
    names = []
    for task in os.listdir("/proc/self/task"):
        try:
            names.append(open(f"/proc/self/task/{task}/comm").read().strip())
        except OSError:
            pass
    return names

with distributed_from_env("cpu") as dist:
    torch.optim.Adam([torch.nn.Parameter(torch.ones(2))])  # the first optimizer: imports torch._dynamo
    dist.all_reduce_sum_(torch.ones(3))
left = [name for name in threads() if "gloo" in name]
print(f"rank {dist.rank}: gloo threads left {left}")
sys.exit(1 if left else 0)
"""


@pytest.mark.slow
def test_the_process_group_is_gone_when_the_context_exits(tmp_path: Path):
    """No gloo thread outlives the context: one left for interpreter shutdown now and then aborts a rank at exit."""
    if not torch.distributed.is_available() or not Path("/proc/self/task").is_dir():
        pytest.skip("needs torch.distributed and Linux's /proc")
    script = tmp_path / "worker.py"
    script.write_text(WORKER)
    env = torchrun_env()
    done = subprocess.run([sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node", "2",
                           str(script)], cwd=REPO, env=env, capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, (done.stdout + done.stderr)[-3000:]
    assert done.stdout.count("gloo threads left []") == 2, done.stdout
