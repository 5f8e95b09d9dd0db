"""``nerfmeta meta-train``: meta-learn an initialisation (MAML, FOMAML, Reptile) over a collection.

The options are the fields of :class:`pretrain.meta.MetaConfig`, and their help is the fields'
docstrings. Every option defaults to "not given", so ``--resume`` can take the saved value of
anything not given again (and refuse a given value that would change what is learned).
"""

from __future__ import annotations

import argparse
import ast
import importlib.util
import inspect
import re
import textwrap
from pathlib import Path
from typing import Any

from nerfmeta.errors import ConfigError, NerfmetaError

DESCRIPTION = """\
Meta-learn an initialisation of a backbone over the training scenes of COLLECTION (each scene a
task: support rays for the inner SGD loop, query rays for the outer loss) and write it to RUN as
an initialisation that 'nerfmeta fit SCENE --init meta:RUN' starts from.

Algorithms per backbone: nerf (MLP) supports maml (exact second order), fomaml and reptile; grid
supports fomaml and reptile only: its feature-grid lookup (embedding_bag) has no double backward
in PyTorch, and grid Hessian-vector products would be very costly. The grid is meta-learned in
one fixed fine stage (no coarse stage, growth or empty-space skipping).

Writes RUN/config.json, metrics.jsonl (per meta-step), checkpoint.safetensors (atomic; --resume
continues after a kill), model.safetensors + init.json (the initialisation), summary.json and
query_psnr_vs_step.png.

Several processes: torchrun --nproc_per_node N -m nerfmeta meta-train ... (gloo on CPU, NCCL with
--device cuda); the tasks of each meta-batch are split over the processes and the meta-gradients
all-reduced, giving the parameters of a one-process run."""

# option name -> (MetaConfig field, argparse keywords)
_OPTIONS: dict[str, tuple[str, dict[str, Any]]] = {
    "--backbone": ("backbone", {"choices": ("grid", "nerf")}),
    "--algo": ("algo", {"choices": ("maml", "fomaml", "reptile")}),
    "--engine": ("engine", {"choices": ("torchfunc", "l2l")}),
    "--inner-steps": ("inner_steps", {"type": int, "metavar": "N"}),
    "--inner-lr": ("inner_lr", {"type": float, "metavar": "X"}),
    "--meta-lr": ("meta_lr", {"type": float, "metavar": "X"}),
    "--meta-batch": ("meta_batch", {"type": int, "metavar": "B"}),
    "--support-rays": ("support_rays", {"type": int, "metavar": "N"}),
    "--query-rays": ("query_rays", {"type": int, "metavar": "N"}),
    "--meta-steps": ("meta_steps", {"type": int, "metavar": "N"}),
    "--seed": ("seed", {"type": int, "metavar": "S"}),
    "--checkpoint-every": ("checkpoint_every", {"type": int, "metavar": "N"}),
    "--eval-tasks": ("eval_tasks", {"type": int, "metavar": "N"}),
    "--downscale": ("downscale", {"type": float, "metavar": "F"}),
    "--device": ("device", {"metavar": "DEV"}),
}


def field_docs(cls: type) -> dict[str, str]:
    """Attribute docstrings of a dataclass (the string literal under each field), by field name."""
    tree = ast.parse(textwrap.dedent(inspect.getsource(cls)))
    body = tree.body[0].body  # type: ignore[attr-defined]
    docs = {}
    for node, after in zip(body, body[1:]):
        if isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name) and isinstance(after, ast.Expr) \
                and isinstance(after.value, ast.Constant) and isinstance(after.value.value, str):
            text = re.sub(r":\w+:`([^`]*)`", r"\1", " ".join(after.value.value.split()))
            docs[node.target.id] = text.replace("``", "")
    return docs


def add_parser(subparsers: argparse._SubParsersAction) -> None:
    if importlib.util.find_spec("pretrain") is None:
        # The command lives in the top-level ``pretrain`` package; an install made before it existed
        # does not map it. Register the command anyway so the others keep working, and say why on use.
        p = subparsers.add_parser("meta-train", help="meta-learn an initialisation (unavailable: see 'meta-train -h')",
                                  description="Unavailable: the 'pretrain' package is not importable; reinstall nerfmeta "
                                  "(pip install -e .) so pretrain/ is installed beside nerfmeta/.")
        p.add_argument("rest", nargs=argparse.REMAINDER)
        p.set_defaults(func=_unavailable)
        return
    from pretrain.meta import MetaConfig

    docs = field_docs(MetaConfig)
    defaults = MetaConfig()
    p = subparsers.add_parser(
        "meta-train",
        help="meta-learn an initialisation (maml|fomaml|reptile) over a collection's training scenes",
        description=DESCRIPTION,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("collection", metavar="COLLECTION", help="collection folder (from make-collection) or its collection.json")
    p.add_argument("--out", required=True, metavar="RUN", help="run folder to write (must be new or empty)")
    for option, (name, kwargs) in _OPTIONS.items():
        default = getattr(defaults, name)
        shown = "" if default is None else f" (default {default})"
        p.add_argument(option, dest=name, default=None, help=f"{docs[name]}{shown}", **kwargs)
    p.add_argument("--inner-lr-group", dest="inner_lr_groups", action="append", default=None, metavar="GROUP=X",
                   help=f"{docs['inner_lr_groups']} (repeatable)")
    p.add_argument("--categories", default=None, metavar="A,B,...", help=f"{docs['categories']} (default all)")
    p.add_argument("--no-jitter", dest="jitter", action="store_const", const=False, default=None, help="render tasks without sample jitter")
    p.add_argument("--background", default=None, metavar="COLOUR", help="white, black or R,G,B (default white)")
    p.add_argument("--set", dest="model", action="append", default=None, metavar="KEY=VALUE",
                   help="override a backbone config field, e.g. --set width=128 (repeatable)")
    p.add_argument("--resume", action="store_true", help="continue the run in RUN from its checkpoint (options not given again keep their saved values)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing RUN folder")
    p.set_defaults(func=run)


def _unavailable(args: argparse.Namespace) -> int:
    raise NerfmetaError("the 'pretrain' package is not importable; reinstall nerfmeta (pip install -e .) so pretrain/ is installed")


def _key_values(items: list[str], what: str) -> dict[str, float]:
    out = {}
    for item in items:
        key, sep, value = item.partition("=")
        try:
            out[key] = float(value)
        except ValueError:
            raise ConfigError(f"{what} {item!r}: expected NAME=NUMBER") from None
        if not sep or not key:
            raise ConfigError(f"{what} {item!r}: expected NAME=NUMBER")
    return out


def given_options(args: argparse.Namespace, saved_backbone: str | None) -> dict[str, Any]:
    """The MetaConfig fields given on the command line (parsed), by field name."""
    from nerfmeta.commands.fit import parse_overrides
    from nerfmeta.data.registry import parse_background

    given = {name: getattr(args, name) for name, _ in _OPTIONS.values() if getattr(args, name) is not None}
    if args.jitter is not None:
        given["jitter"] = args.jitter
    if args.categories is not None:
        given["categories"] = tuple(c.strip() for c in args.categories.split(",") if c.strip())
    if args.background is not None:
        given["background"] = parse_background(args.background)
    if args.inner_lr_groups is not None:
        given["inner_lr_groups"] = _key_values(args.inner_lr_groups, "--inner-lr-group")
    if args.model is not None:
        from nerfmeta.fields.registry import BACKBONES
        from pretrain.meta import MetaConfig

        backbone = given.get("backbone") or saved_backbone or MetaConfig().backbone
        if backbone not in BACKBONES:
            raise ConfigError(f"unknown backbone {backbone!r}; choose one of {', '.join(BACKBONES)}")
        given["model"] = parse_overrides(args.model, backbone)
    return given


class ProgressBar:
    """tqdm bar over meta-steps showing the query PSNR after adaptation and the time.

    The bar appears with the first finished meta-step, so an input error stays a single line.
    """

    def __init__(self, total: int):
        self.total = total
        self.bar = None

    def __call__(self, record) -> None:
        if self.bar is None:
            from tqdm import tqdm

            self.bar = tqdm(total=self.total, initial=record.step - 1, unit="step", dynamic_ncols=True, leave=True, desc="meta-train")
        self.bar.n = record.step
        self.bar.set_postfix({"step": record.step, "query": f"{record.query_psnr:.2f}dB", "init": f"{record.init_psnr:.2f}dB",
                              "t": f"{record.time_s:.1f}s"}, refresh=False)
        self.bar.refresh()

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()


def run(args: argparse.Namespace) -> int:
    from pretrain.meta import MetaConfig
    from pretrain.meta_dist import distributed_from_env
    from pretrain.meta_run import CONFIG, check_resumable, meta_train, resume_config, saved_config

    if args.resume and args.overwrite:
        raise ConfigError("--resume and --overwrite cannot be combined")
    if args.resume:
        if not (Path(args.out) / CONFIG).is_file():
            raise ConfigError(f"{args.out}: nothing to resume (no {CONFIG} there)")
        saved = saved_config(args.out)
        given = given_options(args, saved.backbone)
        if "model" in given:
            given["model"] = {**saved.model, **given["model"]}
        config = resume_config(args.out, given)
        check_resumable(saved, config, Path(args.out))  # before validation: name the changed setting
    else:
        config = MetaConfig(**given_options(args, None))
    config.validate()
    with distributed_from_env(config.device) as dist:
        bar = ProgressBar(config.meta_steps) if dist.is_main else None
        try:
            summary = meta_train(config, args.collection, args.out, resume=args.resume, overwrite=args.overwrite,
                                 progress=bar, dist=dist)
        finally:
            if bar is not None:
                bar.close()
        if not dist.is_main:
            return 0
    held = summary.get("held_out")
    held_text = (f"; held-out {held['split']} scenes: query PSNR {held['query_psnr_before']:.2f} -> {held['query_psnr_after']:.2f} dB "
                 f"after {held['inner_steps']} inner steps") if held else ""
    print(f"{summary['algo']} on {summary['backbone']}: {summary['meta_steps']} meta-steps in {summary['time_s']:.1f} s, "
          f"query PSNR {summary['final_query_psnr']} dB (last 10 steps){held_text}")
    print(f"results in {args.out}/ (init.json, model.safetensors, metrics.jsonl, query_psnr_vs_step.png); "
          f"start a fit from it with: nerfmeta fit SCENE --init meta:{args.out}")
    return 0

