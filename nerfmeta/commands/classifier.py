"""``nerfmeta classifier train``: train the ResNet scene classifier with an "unknown" answer."""

from __future__ import annotations

import argparse
import sys

from classifier.config import ARCHITECTURES, SCORES, STEMS, TrainConfig
from nerfmeta.data.registry import parse_background
from nerfmeta.errors import ConfigError

_DEFAULT = TrainConfig()


def add_parser(subparsers: argparse._SubParsersAction) -> None:
    group = subparsers.add_parser(
        "classifier",
        help="train the scene classifier (sub-commands: train)",
        description="The ResNet scene classifier that names a scene's category or answers 'unknown'.",
    )
    sub = group.add_subparsers(dest="classifier_command", metavar="SUBCOMMAND")
    sub.required = True
    p = sub.add_parser(
        "train",
        help="train a classifier on a collection's training scenes and calibrate its unknown threshold",
        description=(
            "Train a torchvision ResNet on every view of COLLECTION's 'train' scenes, labelled by category, "
            "calibrate the unknown-category threshold on the 'val' scenes of the known categories, and write "
            "model.safetensors, classifier.json (categories, input size, normalisation, threshold, recipe, "
            "validation metrics), history.json and training_curve.png into DIR. Test scenes are not used."
        ),
    )
    p.add_argument("collection", metavar="COLLECTION", help="collection folder (from 'nerfmeta make-collection') or its collection.json")
    p.add_argument("--out", required=True, metavar="DIR", help="classifier folder to write (absent or empty)")
    p.add_argument("--arch", choices=ARCHITECTURES, default=_DEFAULT.arch, help=f"backbone (default {_DEFAULT.arch})")
    p.add_argument("--epochs", type=int, default=_DEFAULT.epochs, metavar="N", help=f"passes over the training views (default {_DEFAULT.epochs})")
    p.add_argument("--holdout-categories", default="", metavar="A,B", help="categories left out of training, to measure unknown detection on")
    p.add_argument("--batch-size", type=int, default=_DEFAULT.batch_size, metavar="N", help=f"views per step (default {_DEFAULT.batch_size})")
    p.add_argument("--lr", type=float, default=_DEFAULT.lr, help=f"peak AdamW learning rate (default {_DEFAULT.lr:g})")
    p.add_argument("--time-budget", type=float, default=None, metavar="S", help="stop optimising after S seconds (the schedule follows time)")
    p.add_argument("--score", choices=("auto", *SCORES), default=_DEFAULT.score, help="unknown score used by the decision; auto (default) picks the best validation AUROC on held-out categories' val scenes, else class_mahalanobis (all are calibrated and reported)")
    p.add_argument("--keep-fraction", type=float, default=_DEFAULT.keep_fraction, metavar="F", help=f"fraction of known validation scenes the threshold keeps (default {_DEFAULT.keep_fraction:g})")
    p.add_argument("--input-size", type=int, default=_DEFAULT.input_size, metavar="PX", help=f"network input side in pixels (default {_DEFAULT.input_size})")
    p.add_argument("--stem", choices=STEMS, default=_DEFAULT.stem, help=f"ResNet stem: torchvision's 7x7/2 conv + max-pool, or a 3x3 conv of stride 2 or 1 without max-pool (more resolution, more compute; default {_DEFAULT.stem})")
    p.add_argument("--background", default="white", metavar="COLOUR", help="white, black or R,G,B views are composited on (default white)")
    p.add_argument("--weights", default=None, metavar="FILE", help="local pretrained torchvision ResNet state dict (.pth or .safetensors); fc is skipped")
    p.add_argument("--seed", type=int, default=_DEFAULT.seed, help=f"seed of weights, shuffling and augmentations (default {_DEFAULT.seed})")
    p.add_argument("--device", default=_DEFAULT.device, help="cpu, cuda or cuda:N (default cpu)")
    p.add_argument("--threads", type=int, default=None, metavar="N", help="torch CPU threads (default: torch's choice)")
    p.add_argument("--overwrite", action="store_true", help="replace DIR if it already holds a classifier")
    p.set_defaults(func=run_train)


def parse_names(text: str) -> tuple[str, ...]:
    """``"a,b"`` -> ``("a", "b")``; empty text -> ``()``."""
    return tuple(n.strip() for n in text.split(",") if n.strip())


class ProgressBar:
    """tqdm bars: one over scenes while reading, one over steps while training."""

    def __init__(self) -> None:
        self.bar = None
        self.stage = None

    def _open(self, stage: str, total: int, unit: str, desc: str) -> None:
        from tqdm import tqdm

        if self.bar is not None:
            self.bar.close()
        self.stage = stage
        self.bar = tqdm(total=total, unit=unit, desc=desc, file=sys.stderr, dynamic_ncols=True)

    def __call__(self, event) -> None:
        if event.stage == "load":
            if self.stage != "load":
                self._open("load", event.total, "scene", "reading views")
            self.bar.n = event.loaded
            self.bar.refresh()
        elif event.stage == "step":
            if self.stage != "step":
                self._open("step", event.total_steps, "step", "training")
            self.bar.n = event.step
            self.bar.set_postfix({"epoch": f"{event.epoch:.2f}", "loss": f"{event.loss:.3f}", "t": f"{event.time_s:.0f}s"}, refresh=False)
            self.bar.refresh()
        elif event.stage == "epoch":
            self.bar.write(f"epoch {event.epoch:.2f}: loss {event.loss:.4f}, validation scene accuracy {event.val_accuracy:.3f}",
                           file=sys.stderr)
        elif event.stage == "calibrate":
            self.close()
            print("calibrating the unknown threshold on validation scenes", file=sys.stderr)

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()
            self.bar = None


def run_train(args: argparse.Namespace) -> int:
    if args.threads is not None and args.threads < 1:
        raise ConfigError(f"--threads must be a positive integer, got {args.threads}")
    config = TrainConfig(
        arch=args.arch,
        stem=args.stem,
        input_size=args.input_size,
        background=parse_background(args.background),
        epochs=args.epochs,
        batch_size=args.batch_size,
        lr=args.lr,
        time_budget_s=args.time_budget,
        seed=args.seed,
        holdout_categories=parse_names(args.holdout_categories),
        score=args.score,
        keep_fraction=args.keep_fraction,
        weights=args.weights,
        device=args.device,
    )
    config.validate()

    import torch

    from classifier.train import train_classifier

    if args.threads is not None:
        torch.set_num_threads(args.threads)
    bar = ProgressBar()
    try:
        doc = train_classifier(config, args.collection, args.out, overwrite=args.overwrite, callbacks=[bar])
    finally:
        bar.close()
    val = doc["validation"]
    score = doc["unknown"]["score"]
    chosen = val["scores"][score]
    held = ""
    if "holdout_val_auroc" in chosen:
        held = (f", held-out val scenes flagged {chosen['holdout_val_detection_rate']:.1%} "
                f"(AUROC {chosen['holdout_val_auroc']:.3f})")
    t = doc["training"]
    print(f"validation: {val['val_scene_accuracy']:.1%} of {val['val_scenes']} scenes right, "
          f"{chosen['val_false_unknown_rate']:.1%} flagged unknown ({score} < {chosen['threshold']:.4g}; {val['score_selection']['rule']}){held}")
    print(f"trained {t['steps']} steps ({t['epochs_done']:.2f} epochs, {t['stop_reason']}) in "
          f"{t['optimisation_time_s']:.0f} s; total {t['wall_time_s']:.0f} s")
    print(f"classifier in {args.out}/ (model.safetensors, classifier.json, history.json, training_curve.png)")
    return 0
