"""Tasks for meta-learning: seeded support/query ray batches drawn from a collection's scenes.

A meta-batch is a pure function of ``(seed, meta-step)``: which scenes it holds, and each task's
rays and jitter seed are a function of ``(seed, meta-step, slot)``. So every process of a
distributed run, and a run resumed after a kill, sees exactly the tasks an uninterrupted
single-process run sees; a process only builds the slots it works on.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Sequence

import torch

from nerfmeta.collection.generate import Collection, SceneRecord
from nerfmeta.data import load_scene
from nerfmeta.errors import ConfigError
from nerfmeta.fit.sampler import RaySampler
from pretrain.meta import Task, derive_seed

log = logging.getLogger(__name__)

_SCENE_STREAM = 0  # derive_seed(seed, _SCENE_STREAM, step): which scenes a meta-batch holds
_TASK_STREAM = 1  # derive_seed(seed, _TASK_STREAM, step, slot): a task's rays and jitter
_EVAL_STREAM = 2  # derive_seed(seed, _EVAL_STREAM, index): held-out evaluation tasks


@dataclass(frozen=True)
class TaskScene:
    """A scene that tasks are drawn from: its record and a sampler over its training views."""

    record: SceneRecord
    sampler: RaySampler


def select_scenes(collection: Collection, split: str, categories: Sequence[str] = ()) -> list[SceneRecord]:
    """The collection's scenes of ``split`` (and of ``categories`` when given), sorted by name."""
    known = sorted({s.category for s in collection.scenes})
    unknown = [c for c in categories if c not in known]
    if unknown:
        raise ConfigError(f"--categories {','.join(unknown)}: not in {collection.root} (it has {', '.join(known)})")
    return [s for s in collection.scenes if s.split == split and (not categories or s.category in categories)]


def load_task_scenes(collection: Collection, records: Sequence[SceneRecord], *, device: torch.device | str,
                     downscale: float = 1.0, background: tuple[float, float, float] = (1.0, 1.0, 1.0)) -> list[TaskScene]:
    """Load each scene's training views into a :class:`RaySampler` on ``device``."""
    scenes = []
    for record in records:
        scene = load_scene(collection.scene_path(record), downscale=downscale, background=background)
        if not scene.splits.get("train"):
            raise ConfigError(f"{collection.scene_path(record)}: the scene has no training views")
        scenes.append(TaskScene(record, RaySampler(scene, "train", device)))
    return scenes


class TaskSampler:
    """Deterministic meta-batches over a fixed list of scenes.

    Args:
        scenes: the scenes tasks are drawn from (their order matters: keep it sorted by name).
        seed: the run's seed.
        support_rays, query_rays: rays per support and query batch.
    """

    def __init__(self, scenes: Sequence[TaskScene], seed: int, support_rays: int, query_rays: int):
        if not scenes:
            raise ValueError("no scenes to draw tasks from")
        self.scenes = list(scenes)
        self.seed = seed
        self.support_rays = support_rays
        self.query_rays = query_rays

    def scene_indices(self, step: int, meta_batch: int) -> list[int]:
        """Scene of each slot of meta-step ``step``: distinct scenes while the batch fits, then repeats."""
        gen = torch.Generator().manual_seed(derive_seed(self.seed, _SCENE_STREAM, step))
        n = len(self.scenes)
        order: list[int] = []
        while len(order) < meta_batch:
            order += torch.randperm(n, generator=gen).tolist()
        return order[:meta_batch]

    def task(self, scene_index: int, key: tuple[int, ...]) -> Task:
        """The task of scene ``scene_index`` whose rays and jitter come from ``derive_seed(seed, *key)``."""
        gen = torch.Generator().manual_seed(derive_seed(self.seed, *key))
        scene = self.scenes[scene_index]
        support = scene.sampler.sample(self.support_rays, gen)
        query = scene.sampler.sample(self.query_rays, gen)
        jitter_seed = int(torch.randint(0, 2**62, (1,), generator=gen))
        return Task(scene.record.name, support, query, jitter_seed)

    def tasks(self, step: int, meta_batch: int, rank: int = 0, world_size: int = 1) -> list[Task]:
        """The tasks of meta-step ``step`` that process ``rank`` of ``world_size`` works on: slots
        ``rank, rank + world_size, ...`` of the meta-batch."""
        indices = self.scene_indices(step, meta_batch)
        return [self.task(indices[slot], (_TASK_STREAM, step, slot)) for slot in range(rank, meta_batch, world_size)]

    def eval_tasks(self, count: int) -> list[Task]:
        """One task for each of the first ``count`` scenes (held-out evaluation), seeded by position."""
        return [self.task(i, (_EVAL_STREAM, i)) for i in range(min(count, len(self.scenes)))]

