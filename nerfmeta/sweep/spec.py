"""The SPEC of ``nerfmeta sweep``: a small YAML or JSON file, read and checked before anything is written.

Example (YAML)::

    scenes: [lego]                 # scene folders or files, relative to the SPEC's folder
    backbone: grid
    fixed:                         # settings every trial shares: fields of the fit, run or backbone config
      iters: 400
      downscale: 8
    search:                        # the knobs: any fit/run/backbone config field
      batch_rays: {values: [1024, 4096, 8192], default: 4096}     # categorical
      num_voxels: {int: [20000, 200000], log: true}               # integer range
      lr_decay: {float: [0.01, 0.5], log: true}                   # float range
    objectives: {test_psnr: max, time_s: min, peak_rss_mb: min}
    sampler: grid                  # grid (one knob at a time around the defaults), random, tpe, nsga2
    repeats: 2                     # seeds per configuration
    n_trials: 20                   # configurations to try (grid: set by the design)
    combinations:                  # grid: extra configurations, e.g. the best knobs together
      - {batch_rays: 8192, num_voxels: 200000}

A knob's name is a field of :class:`~nerfmeta.fit.loop.FitConfig`, of
:class:`~nerfmeta.fit.run.RunConfig` or of the backbone's config; ``fit.NAME``, ``run.NAME`` or
``model.NAME`` picks one where a name is in several. Every value is checked by the same code that
checks the command line (type and declared range), so a bad SPEC is one line naming the field.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

from nerfmeta.config import did_you_mean
from nerfmeta.errors import ConfigError, message_line

SAMPLERS = ("grid", "random", "tpe", "nsga2")
"""Samplers a SPEC may name; ``grid`` is the one-at-a-time design of the source study."""

OBJECTIVES = ("test_psnr", "test_ssim", "test_lpips", "time_s", "eval_time_s", "peak_rss_mb", "wall_s",
              "samples_per_ray", "train_samples_per_ray", "n_parameters", "iters")
"""Figures a trial reports (the fit's ``summary.json`` plus the sweep's own per-process measurements)."""

TOP_KEYS = ("scenes", "scene", "backbone", "fixed", "search", "objectives", "sampler", "repeats", "n_trials",
            "combinations", "seed", "name")
RUN_FIELDS = ("downscale", "normalize", "background", "device", "renders")
"""The :class:`RunConfig` fields a SPEC may set (the scene, init and freeze are the sweep's own business)."""


@dataclass(frozen=True)
class Knob:
    """One searched field and its distribution."""

    name: str
    """The name as written in the SPEC."""
    section: Literal["fit", "run", "model"]
    """Which config the field belongs to."""
    field: str
    """The field's name in that config."""
    kind: Literal["categorical", "int", "float"]
    """The distribution."""
    values: tuple[Any, ...] = ()
    """Categorical values, in the SPEC's order."""
    low: float | None = None
    """Lower end of a range (included)."""
    high: float | None = None
    """Upper end of a range (included)."""
    log: bool = False
    """Sample the range on a log scale."""
    default: Any = None
    """The knob's value in the default configuration (the SPEC's ``default``, else the config's)."""


@dataclass(frozen=True)
class SweepSpec:
    """A checked SPEC (see the module docstring); saved as ``DIR/spec.json``."""

    scenes: tuple[str, ...]
    """Scene folders or files (absolute)."""
    backbone: str
    """Backbone of every trial."""
    fixed: dict[str, dict[str, Any]]
    """Fixed settings by section (``fit``, ``run``, ``model``)."""
    knobs: tuple[Knob, ...]
    """The searched fields."""
    objectives: tuple[tuple[str, str], ...]
    """(figure, ``max`` or ``min``) pairs."""
    sampler: str = "grid"
    """grid, random, tpe or nsga2."""
    repeats: int = 1
    """Seeds per configuration (0, 1, ... added to the fit seed)."""
    n_trials: int | None = None
    """Configurations to try (grid: the design's size)."""
    combinations: tuple[dict[str, Any], ...] = ()
    """Extra configurations of the grid design."""
    seed: int = 0
    """Seed of the sampler."""
    name: str | None = None
    """Study name (default: from the SPEC's hash)."""

    def as_json(self) -> dict[str, Any]:
        return json.loads(json.dumps(dataclasses.asdict(self)))

    @staticmethod
    def from_json(data: dict[str, Any]) -> "SweepSpec":
        knobs = tuple(Knob(**{**k, "values": tuple(k["values"])}) for k in data["knobs"])
        return SweepSpec(**{**data, "scenes": tuple(data["scenes"]), "knobs": knobs,
                            "objectives": tuple(tuple(o) for o in data["objectives"]),
                            "combinations": tuple(data.get("combinations", ()))})

    def digest(self) -> str:
        """SHA-256 of the canonical JSON form: the same SPEC gives the same study."""
        return hashlib.sha256(json.dumps(self.as_json(), sort_keys=True).encode()).hexdigest()

    def study_name(self) -> str:
        return self.name or f"sweep-{self.digest()[:12]}"

    @property
    def directions(self) -> list[str]:
        return ["maximize" if d == "max" else "minimize" for _, d in self.objectives]

    def default_params(self) -> dict[str, Any]:
        """Every knob at its default value."""
        return {k.name: k.default for k in self.knobs}

    def grid_plan(self) -> list[dict[str, Any]]:
        """The one-at-a-time design: the defaults, each knob's other values with the rest at default, then
        the ``combinations`` (duplicates dropped, order kept)."""
        base = self.default_params()
        plan = [base]
        for knob in self.knobs:
            plan += [{**base, knob.name: v} for v in knob.values if v != knob.default]
        plan += [{**base, **c} for c in self.combinations]
        unique: list[dict[str, Any]] = []
        for p in plan:
            if p not in unique:
                unique.append(p)
        return unique

    def planned_trials(self) -> int:
        return len(self.grid_plan()) if self.sampler == "grid" else int(self.n_trials or 0)

    def run_values(self, params: dict[str, Any]) -> dict[str, dict[str, Any]]:
        """The fixed settings with ``params`` (knob name -> value) applied, by section."""
        out = {s: dict(v) for s, v in self.fixed.items()}
        for knob in self.knobs:
            if knob.name in params:
                out.setdefault(knob.section, {})[knob.field] = params[knob.name]
        return out


# ---------------------------------------------------------------------------------------------------
# Reading and checking


def _sections(backbone: str) -> dict[str, dict[str, dataclasses.Field]]:
    from nerfmeta.fields.registry import BACKBONES
    from nerfmeta.fit.loop import FitConfig
    from nerfmeta.fit.run import RunConfig

    run_fields = {f.name: f for f in dataclasses.fields(RunConfig) if f.name in RUN_FIELDS}
    return {"fit": {f.name: f for f in dataclasses.fields(FitConfig) if f.name != "seed"},
            "run": run_fields,
            "model": {f.name: f for f in dataclasses.fields(BACKBONES[backbone][0])}}


def resolve_field(name: str, backbone: str, where: str) -> tuple[str, str]:
    """(section, field) of a SPEC key such as ``iters``, ``fit.iters`` or ``model.num_voxels``."""
    sections = _sections(backbone)
    section, dot, field = name.rpartition(".")
    if dot:
        if section not in sections:
            raise ConfigError(f"{where}.{name}: unknown section {section!r}; use fit., run. or model.")
        if field not in sections[section]:
            raise ConfigError(f"{where}.{name}: unknown field{did_you_mean(field, list(sections[section]))}")
        return section, field
    found = [s for s in sections if name in sections[s]]
    if not found:
        known = [f for s in sections.values() for f in s]
        hint = did_you_mean(name, known) or (" (the fit seed is set by repeats)" if name == "seed" else "")
        raise ConfigError(f"{where}.{name}: unknown field{hint}")
    if len(found) > 1:
        raise ConfigError(f"{where}.{name}: a field of the {' and '.join(found)} configs; write "
                          + " or ".join(f"{s}.{name}" for s in found))
    return found[0], name


def check_values(backbone: str, values: dict[str, dict[str, Any]], where: str) -> None:
    """Build the three configs from ``values`` (by section) so that their own checks run; one line naming ``where``."""
    from nerfmeta.fields.registry import config_from_dict, default_config
    from nerfmeta.fit.loop import FitConfig
    from nerfmeta.fit.run import RunConfig

    try:
        FitConfig(**values.get("fit", {}))
        RunConfig(scene=".", **{k: tuple(v) if isinstance(v, list) else v for k, v in values.get("run", {}).items()})
        base = dataclasses.asdict(default_config(backbone))
        config_from_dict(backbone, {**base, **values.get("model", {})})
    except (ConfigError, TypeError, ValueError) as err:
        raise ConfigError(f"{where}: {message_line(err)}") from None


def _field_default(section: str, field: str, backbone: str) -> Any:
    from nerfmeta.fields.registry import default_config
    from nerfmeta.fit.loop import FitConfig
    from nerfmeta.fit.run import RunConfig

    if section == "model":
        return getattr(default_config(backbone), field)
    return getattr(FitConfig() if section == "fit" else RunConfig(scene="."), field)


def _number(value: Any, where: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise ConfigError(f"{where}: {value!r} is not a finite number")
    return float(value)


def _knob(name: str, doc: Any, backbone: str, fixed: dict[str, dict[str, Any]]) -> Knob:
    where = f"search.{name}"
    section, field = resolve_field(name, backbone, "search")
    if not isinstance(doc, dict):
        doc = {"values": doc} if isinstance(doc, list) else None
    if doc is None:
        raise ConfigError(f"{where}: expected {{values: [...]}}, {{int: [low, high]}} or {{float: [low, high]}}")
    kinds = [k for k in ("values", "int", "float") if k in doc]
    extra = sorted(set(doc) - {"values", "int", "float", "log", "default"})
    if extra:
        raise ConfigError(f"{where}.{extra[0]}: unknown key{did_you_mean(extra[0], ['values', 'int', 'float', 'log', 'default'])}")
    if len(kinds) != 1:
        raise ConfigError(f"{where}: give exactly one of values, int or float")
    kind = kinds[0]
    log = doc.get("log", False)
    if not isinstance(log, bool):
        raise ConfigError(f"{where}.log: expected true or false, got {log!r}")
    if kind == "values":
        values = doc["values"]
        if not isinstance(values, list) or not values:
            raise ConfigError(f"{where}.values: empty; list at least one value")
        values = tuple(tuple(v) if isinstance(v, list) else v for v in values)
        for v in values:
            check_values(backbone, {**fixed, section: {**fixed.get(section, {}), field: v}}, f"{where}.values {v!r}")
        default = doc.get("default", fixed.get(section, {}).get(field, _field_default(section, field, backbone)))
        if "default" not in doc and default not in values:
            default = values[0]
        return Knob(name, section, field, "categorical", values=values, default=default)
    bounds = doc[kind]
    if not isinstance(bounds, list) or len(bounds) != 2:
        raise ConfigError(f"{where}.{kind}: expected [low, high]")
    low, high = (_number(b, f"{where}.{kind}") for b in bounds)
    if kind == "int" and not (low.is_integer() and high.is_integer()):
        raise ConfigError(f"{where}.int: [{bounds[0]}, {bounds[1]}] are not whole numbers")
    if not low < high:
        raise ConfigError(f"{where}.{kind}: empty range [{bounds[0]}, {bounds[1]}] (low must be below high)")
    if log and low <= 0:
        raise ConfigError(f"{where}.{kind}: a log range needs low > 0, got {bounds[0]}")
    cast = int if kind == "int" else float
    for v in (cast(low), cast(high)):
        check_values(backbone, {**fixed, section: {**fixed.get(section, {}), field: v}}, f"{where}.{kind} {v!r}")
    default = doc.get("default", fixed.get(section, {}).get(field, _field_default(section, field, backbone)))
    if isinstance(default, bool) or not isinstance(default, (int, float)) or not low <= default <= high:
        default = cast(math.sqrt(low * high)) if log else cast((low + high) / 2)
    return Knob(name, section, field, kind, low=cast(low), high=cast(high), log=log, default=cast(default))


def load_spec(path: str | Path) -> SweepSpec:
    """Read and check a SPEC file; raise a one-line :class:`ConfigError` naming the field at fault."""
    path = Path(path)
    try:
        text = path.read_text()
    except OSError as err:
        raise ConfigError(f"{path}: cannot read the SPEC ({err.strerror})") from None
    try:
        if path.suffix.lower() == ".json":
            doc = json.loads(text)
        else:
            import yaml

            doc = yaml.safe_load(text)
    except Exception as err:  # noqa: BLE001 - any parse error is the user's file
        raise ConfigError(f"{path}: not valid {'JSON' if path.suffix.lower() == '.json' else 'YAML'} "
                          f"({' '.join(str(err).split())[:200]})") from None
    if not isinstance(doc, dict):
        raise ConfigError(f"{path}: expected a mapping of {', '.join(TOP_KEYS)}")
    try:
        return parse_spec(doc, path.parent)
    except ConfigError as err:
        raise ConfigError(f"{path}: {err}") from None


def parse_spec(doc: dict[str, Any], base: Path) -> SweepSpec:
    """Check a SPEC's mapping (relative scene paths are taken from ``base``)."""
    from nerfmeta.fields.registry import BACKBONES

    for key in doc:
        if key not in TOP_KEYS:
            raise ConfigError(f"{key}: unknown field{did_you_mean(str(key), list(TOP_KEYS))}")
    scenes = doc.get("scenes", doc.get("scene"))
    if isinstance(scenes, str):
        scenes = [scenes]
    if not isinstance(scenes, list) or not scenes or not all(isinstance(s, str) for s in scenes):
        raise ConfigError("scenes: expected a list of scene folders")
    scenes = [str((base / s).resolve()) for s in scenes]
    for s in scenes:
        if not Path(s).exists():
            raise ConfigError(f"scenes: {s} does not exist")
    backbone = doc.get("backbone", "grid")
    if backbone not in BACKBONES:
        raise ConfigError(f"backbone: {backbone!r} is not one of {', '.join(BACKBONES)}{did_you_mean(str(backbone), list(BACKBONES))}")
    fixed: dict[str, dict[str, Any]] = {}
    raw_fixed = doc.get("fixed") or {}
    if not isinstance(raw_fixed, dict):
        raise ConfigError("fixed: expected a mapping of field: value")
    for name, value in raw_fixed.items():
        section, field = resolve_field(str(name), backbone, "fixed")
        fixed.setdefault(section, {})[field] = tuple(value) if isinstance(value, list) else value
        check_values(backbone, fixed, f"fixed.{name}")
    raw_search = doc.get("search") or {}
    if not isinstance(raw_search, dict) or not raw_search:
        raise ConfigError("search: expected at least one knob (field: {values: [...]} or {int|float: [low, high]})")
    knobs = tuple(_knob(str(n), d, backbone, fixed) for n, d in raw_search.items())
    objectives = _objectives(doc.get("objectives", {"test_psnr": "max", "time_s": "min", "peak_rss_mb": "min"}))
    sampler = doc.get("sampler", "grid")
    if sampler not in SAMPLERS:
        raise ConfigError(f"sampler: {sampler!r} is not one of {', '.join(SAMPLERS)}{did_you_mean(str(sampler), list(SAMPLERS))}")
    repeats = _count(doc.get("repeats", 1), "repeats")
    n_trials = doc.get("n_trials")
    if sampler == "grid":
        bad = [k.name for k in knobs if k.kind != "categorical"]
        if bad:
            raise ConfigError(f"search.{bad[0]}: the grid sampler needs a list of values ({{values: [...]}})")
    elif n_trials is None:
        raise ConfigError(f"n_trials: required with the {sampler} sampler")
    if n_trials is not None:
        n_trials = _count(n_trials, "n_trials")
    combinations = doc.get("combinations") or []
    if not isinstance(combinations, list) or not all(isinstance(c, dict) for c in combinations):
        raise ConfigError("combinations: expected a list of {knob: value} mappings")
    names = {k.name: k for k in knobs}
    for i, combo in enumerate(combinations):
        for name, value in combo.items():
            if name not in names:
                raise ConfigError(f"combinations[{i}].{name}: not a knob of search{did_you_mean(str(name), list(names))}")
            knob = names[name]
            check_values(backbone, {**fixed, knob.section: {**fixed.get(knob.section, {}), knob.field: value}},
                         f"combinations[{i}].{name}")
    seed = doc.get("seed", 0)
    if isinstance(seed, bool) or not isinstance(seed, int):
        raise ConfigError(f"seed: expected a whole number, got {seed!r}")
    name = doc.get("name")
    if name is not None and not (isinstance(name, str) and name):
        raise ConfigError(f"name: expected a non-empty string, got {name!r}")
    return SweepSpec(tuple(scenes), backbone, fixed, knobs, objectives, sampler, repeats, n_trials,
                     tuple({k: tuple(v) if isinstance(v, list) else v for k, v in c.items()} for c in combinations),
                     seed, name)


def _count(value: Any, where: str) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or value < 1:
        raise ConfigError(f"{where}: expected a whole number >= 1, got {value!r}")
    return value


def _objectives(raw: Any) -> tuple[tuple[str, str], ...]:
    """``{test_psnr: max, time_s: min}`` or ``["max test_psnr", "min time_s"]`` -> pairs, checked."""
    if isinstance(raw, list):
        pairs = []
        for item in raw:
            words = str(item).split()
            if len(words) != 2 or words[0] not in ("max", "min"):
                raise ConfigError(f"objectives: {item!r}: expected 'max FIGURE' or 'min FIGURE'")
            pairs.append((words[1], words[0]))
    elif isinstance(raw, dict):
        pairs = [(str(k), str(v)) for k, v in raw.items()]
    else:
        raise ConfigError("objectives: expected {figure: max|min, ...}")
    if not pairs:
        raise ConfigError("objectives: name at least one figure")
    for figure, direction in pairs:
        if figure not in OBJECTIVES:
            raise ConfigError(f"objectives.{figure}: not a figure a fit reports{did_you_mean(figure, list(OBJECTIVES))} "
                              f"(known: {', '.join(OBJECTIVES)})")
        if direction not in ("max", "min"):
            raise ConfigError(f"objectives.{figure}: {direction!r} is not max or min")
    if len({f for f, _ in pairs}) != len(pairs):
        raise ConfigError("objectives: a figure is named twice")
    return tuple(pairs)
