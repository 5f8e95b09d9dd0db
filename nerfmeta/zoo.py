"""The model zoo: a classifier, category models, a meta-learned initialisation and an occupancy network, hash-checked.

A zoo folder (the shipped one is ``model_zoo/`` in the checkout, built by
``scripts/build_model_zoo``) holds::

    manifest.json            {"format", "built_by", "seed", "backbone", "fit", "training_data",
                              "entries": [{"name", "kind", "path", "category", "files": {FILE: SHA-256},
                              "bytes", "config", "metrics"}, ...]}
    classifier/              a 'nerfmeta classifier train' folder (classifier.json, model.safetensors)
    category/CATEGORY/       a 'nerfmeta pretrain category' model (init.json, model.safetensors)
    meta/                    a 'nerfmeta meta-train' initialisation (init.json, model.safetensors)
    occupancy/               the learned occupancy start's network (occupancy.json, model.safetensors;
                             ``fit --init occupancy``, :mod:`nerfmeta.priors.occupancy`); older zoos lack it

As torchvision does for pretrained weights, every file the zoo uses is listed in the manifest
with its SHA-256, and :func:`load_zoo` refuses a zoo in which any listed file is missing or has
another hash, naming the file. ``fit`` holds the fit settings the zoo's models were trained for
(backbone, rays per iteration, ...), which a routed fit and its scratch baseline both use.

Which zoo: ``--zoo DIR``, else the ``NERFMETA_ZOO`` environment variable (``none`` for no zoo),
else the shipped zoo when it has a manifest: installed with the package as ``nerfmeta/model_zoo/``
(``pip install .``), or ``model_zoo/`` of the checkout (an editable install, or no install).
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Sequence

from nerfmeta import validate
from nerfmeta.errors import ConfigError
from nerfmeta.fields.registry import BACKBONES, config_from_dict
from nerfmeta.io import check_sha256, read_json_index, sha256_file, to_jsonable, write_json

ZOO_FORMAT = "nerfmeta-zoo-1"
MANIFEST = "manifest.json"
KINDS = ("classifier", "category", "meta", "occupancy")
ENV = "NERFMETA_ZOO"
PACKAGED_ZOOS = (Path(__file__).resolve().parent / "model_zoo", Path(__file__).resolve().parents[1] / "model_zoo")
"""Where the shipped zoo is, in order: inside the installed package (setup.cfg installs the checkout's
``model_zoo/`` as package data ``nerfmeta/model_zoo/``), then beside the package in a checkout."""


@dataclass(frozen=True)
class ZooEntry:
    """One model of a zoo.

    Attributes:
        name: unique name (``classifier``, ``category/chair``, ``meta``).
        kind: one of :data:`KINDS`.
        path: its folder, absolute.
        category: the category of a category model, else None.
        files: file name (relative to ``path``) -> SHA-256.
        config: how it was trained (recipe).
        metrics: what was measured on it.
    """

    name: str
    kind: str
    path: Path
    category: str | None
    files: dict[str, str]
    config: dict[str, Any]
    metrics: dict[str, Any]


@dataclass(frozen=True)
class Zoo:
    """A loaded, verified zoo.

    Attributes:
        root: the zoo folder.
        manifest: the parsed ``manifest.json``.
        entries: its models.
        fit: the fit settings its models were trained for (``backbone``, ``batch_rays``, ``iters``, ...).
    """

    root: Path
    manifest: dict[str, Any]
    entries: tuple[ZooEntry, ...]
    fit: dict[str, Any]

    @property
    def classifier(self) -> ZooEntry | None:
        return next((e for e in self.entries if e.kind == "classifier"), None)

    @property
    def meta(self) -> ZooEntry | None:
        return next((e for e in self.entries if e.kind == "meta"), None)

    @property
    def occupancy(self) -> ZooEntry | None:
        """The learned occupancy start's network, if the zoo has one."""
        return next((e for e in self.entries if e.kind == "occupancy"), None)

    @property
    def occupancy_net(self) -> Path | None:
        """The occupancy network's file (``occupancy/model.safetensors``), if the zoo has one."""
        return None if self.occupancy is None else self.occupancy.path / "model.safetensors"

    @property
    def categories(self) -> dict[str, ZooEntry]:
        """Category -> its category model."""
        return {e.category: e for e in self.entries if e.kind == "category" and e.category}

    @property
    def backbone(self) -> str:
        return str(self.fit.get("backbone", "nerf"))


def resolve_zoo_path(zoo: str | os.PathLike | None) -> Path | None:
    """The zoo folder to use: ``zoo`` if given, else ``$NERFMETA_ZOO`` (``none``: no zoo), else the packaged one if built."""
    if zoo is not None:
        return None if str(zoo).lower() == "none" else Path(zoo)
    env = os.environ.get(ENV)
    if env is not None and env != "":
        return None if env.lower() == "none" else Path(env)
    return next((path for path in PACKAGED_ZOOS if (path / MANIFEST).is_file()), None)


def load_zoo(root: str | os.PathLike, *, verify: bool = True) -> Zoo:
    """Read ``root/manifest.json`` and (``verify``) check every listed file's SHA-256.

    Raises:
        ConfigError: a missing or unreadable manifest, another format, a field of the wrong type or
            range, an entry without its folder or files or whose path leads out of ``root``, a
            file whose hash differs from the manifest's (one line naming it).
    """
    root = Path(root)
    index = root / MANIFEST
    doc = read_json_index(index, ZOO_FORMAT, what="a nerfmeta model zoo manifest",
                          missing=f"a model zoo folder needs {MANIFEST} (build one with scripts/build_model_zoo)")
    raw_entries = doc.get("entries", [])
    if not isinstance(raw_entries, list) or not raw_entries:
        raise ConfigError(f"{index}: lists no models ('entries' must be a non-empty list)")
    entries = [_entry(root, index, k, raw, verify=verify) for k, raw in enumerate(raw_entries)]
    names = [e.name for e in entries]
    duplicate = next((n for n in names if names.count(n) > 1), None)
    if duplicate is not None:
        raise ConfigError(f"{index}: entry name {duplicate!r} is listed twice")
    return Zoo(root.resolve(), doc, tuple(entries), check_fit_settings(doc.get("fit", {}), where=f"{index}: fit"))


FIT_INTEGERS = {"batch_rays": (1, 1 << 22), "iters": (1, 10_000_000), "eval_every": (0, None), "eval_views": (0, None),
                "freeze": (0, 1000), "trained_resolution": (1, 65536)}
"""Integer fields of a manifest's ``fit`` with their (minimum, maximum)."""


def check_fit_settings(fit: Any, *, where: str) -> dict[str, Any]:
    """A manifest's ``fit`` with every known field checked (type, range; the model overrides against the
    backbone's config). Unknown fields are kept (newer zoos may record more)."""
    fit = dict(validate.mapping(fit, where=where))
    for key, (lo, hi) in FIT_INTEGERS.items():
        if key in fit:
            validate.integer(fit[key], where=f"{where}.{key}", minimum=lo, maximum=hi)
    backbone = validate.text(fit.get("backbone", "nerf"), where=f"{where}.backbone", choices=tuple(BACKBONES))
    model = validate.mapping(fit.get("model", {}), where=f"{where}.model")
    try:
        config_from_dict(backbone, dict(model))
    except ConfigError as err:
        raise ConfigError(f"{where}.model: {err}") from None
    except (TypeError, ValueError) as err:
        raise ConfigError(f"{where}.model: not a valid {backbone} configuration ({err})") from None
    return fit


def _entry(root: Path, index: Path, k: int, raw: Any, *, verify: bool) -> ZooEntry:
    """Entry ``k`` of the manifest, typed and checked; its folder and files must stay inside ``root``."""
    where = f"{index}: entries[{k}]"
    raw = validate.mapping(raw, where=where)
    missing = [key for key in ("name", "kind", "path", "files") if key not in raw]
    if missing:
        raise ConfigError(f"{where} lacks {', '.join(missing)}")
    name = validate.text(raw["name"], where=f"{where}.name")
    where = f"{index}: entry {name!r}"
    kind = validate.text(raw["kind"], where=f"{where}: kind", choices=KINDS)
    category = raw.get("category")
    if kind == "category" or category is not None:
        category = validate.text(category, where=f"{where}: category")
    folder = validate.inside(root, raw["path"], where=f"{where}: path")
    files = validate.mapping(raw["files"], where=f"{where}: files")
    for file, digest in files.items():
        path = validate.inside(folder, file, where=f"{where}: file")
        if verify:
            if not path.is_file():
                raise ConfigError(f"{path}: listed in {index} but missing; restore the zoo (git checkout model_zoo) or rebuild it")
            check_sha256(path, digest, index, "the file was changed or corrupted, refusing the zoo")
    config = validate.mapping(raw.get("config", {}), where=f"{where}: config")
    metrics = validate.mapping(raw.get("metrics", {}), where=f"{where}: metrics")
    return ZooEntry(name, kind, folder, category, dict(files), config, metrics)


def open_zoo(zoo: str | os.PathLike | None) -> Zoo | None:
    """The verified zoo chosen by :func:`resolve_zoo_path`, or None when there is none."""
    path = resolve_zoo_path(zoo)
    return None if path is None else load_zoo(path)


def zoo_entry(root: Path, name: str, kind: str, folder: Path, files: Sequence[str], *, category: str | None = None,
              config: dict[str, Any] | None = None, metrics: dict[str, Any] | None = None) -> dict[str, Any]:
    """A manifest entry for ``folder`` (inside ``root``) listing ``files`` with their hashes and sizes."""
    paths = [folder / f for f in files]
    for p in paths:
        if not p.is_file():
            raise ConfigError(f"{p}: missing, cannot list it in the zoo")
    return {
        "name": name,
        "kind": kind,
        "path": folder.resolve().relative_to(root.resolve()).as_posix(),
        "category": category,
        "files": {f: sha256_file(folder / f) for f in files},
        "bytes": sum(p.stat().st_size for p in paths),
        "config": to_jsonable(config or {}),
        "metrics": to_jsonable(metrics or {}),
    }


def write_manifest(root: str | os.PathLike, entries: Sequence[dict[str, Any]], **fields: Any) -> Path:
    """Write ``root/manifest.json`` (atomically) with ``entries`` and the top-level ``fields``."""
    root = Path(root)
    doc = {"format": ZOO_FORMAT, **to_jsonable(fields), "entries": list(entries),
           "total_bytes": sum(int(e["bytes"]) for e in entries)}
    write_json(root / MANIFEST, doc)
    return root / MANIFEST
