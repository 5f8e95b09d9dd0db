"""Bad SPEC files: one line naming the field, exit 2, nothing written."""

from __future__ import annotations

import json

import pytest

from nerfmeta.cli import main
from nerfmeta.data.synthetic import write_tiny_scene
from nerfmeta.sweep.spec import load_spec

GOOD = {
    "scenes": ["scene"],
    "backbone": "grid",
    "fixed": {"iters": 10, "coarse_iters": 3},
    "search": {"batch_rays": {"values": [64, 128]}},
    "objectives": {"test_psnr": "max", "time_s": "min"},
}


@pytest.fixture(scope="module")
def scene_dir(tmp_path_factory):
    root = tmp_path_factory.mktemp("spec")
    write_tiny_scene(root / "scene")
    return root


def _write(root, doc, name="spec.json"):
    path = root / name
    path.write_text(json.dumps(doc) if name.endswith(".json") else doc)
    return path


def test_a_good_spec_reads_back_with_defaults_and_a_one_at_a_time_plan(scene_dir):
    spec = load_spec(_write(scene_dir, {**GOOD, "search": {"batch_rays": {"values": [64, 4096, 128]},
                                                             "num_voxels": {"values": [1000, 2000]}}}))
    assert spec.fixed == {"fit": {"iters": 10}, "model": {"coarse_iters": 3}}
    assert [k.default for k in spec.knobs] == [4096, 1000]  # the config's default where listed, else the first value
    assert spec.grid_plan() == [{"batch_rays": 4096, "num_voxels": 1000}, {"batch_rays": 64, "num_voxels": 1000},
                                {"batch_rays": 128, "num_voxels": 1000}, {"batch_rays": 4096, "num_voxels": 2000}]
    yaml_spec = load_spec(_write(scene_dir, "scenes: [scene]\nsearch:\n  lr_decay: {float: [0.01, 0.5], log: true}\n"
                                             "sampler: tpe\nn_trials: 3\n", "spec.yaml"))
    assert yaml_spec.knobs[0].kind == "float" and yaml_spec.knobs[0].log and yaml_spec.planned_trials() == 3


BAD = [
    ({"serach": GOOD["search"]}, "serach: unknown field; did you mean 'search'?"),
    ({"search": {"batch_ray": {"values": [64]}}}, "search.batch_ray: unknown field; did you mean 'batch_rays'?"),
    ({"fixed": {"iter": 10}}, "fixed.iter: unknown field; did you mean 'iters'?"),
    ({"search": {"num_voxels": {"int": [5000, 1000]}}, "sampler": "random", "n_trials": 2},
     "search.num_voxels.int: empty range [5000, 1000]"),
    ({"search": {"batch_rays": {"values": []}}}, "search.batch_rays.values: empty"),
    ({"fixed": {"iters": "ten"}}, "fixed.iters: fit config iters='ten': expected int"),
    ({"search": {"batch_rays": {"values": [64, "many"]}}}, "search.batch_rays.values 'many': fit config batch_rays='many'"),
    ({"search": {"lr_decay": {"values": [0.5, 2.0]}}}, "search.lr_decay.values 2.0: fit config lr_decay=2.0: must be in (0, 1]"),
    ({"objectives": {"test_psnr": "max", "train_time": "min"}}, "objectives.train_time: not a figure a fit reports"),
    ({"objectives": {"test_psnr": "biggest"}}, "objectives.test_psnr: 'biggest' is not max or min"),
    ({"sampler": "tpe"}, "n_trials: required with the tpe sampler"),
    ({"sampler": "cmaes"}, "sampler: 'cmaes' is not one of"),
    ({"search": {"lr_decay": {"float": [0.1, 0.5]}}}, "search.lr_decay: the grid sampler needs a list of values"),
    ({"repeats": 0}, "repeats: expected a whole number >= 1"),
]


@pytest.mark.parametrize("change,needle", BAD, ids=[b[1].split(":")[0] for b in BAD])
def test_a_bad_spec_is_one_line_exit_2_and_writes_nothing(scene_dir, tmp_path, capsys, change, needle):
    doc = {**GOOD, **change}
    if "serach" in change:
        del doc["search"]
    spec = _write(scene_dir, doc)
    out = tmp_path / "out"
    assert main(["sweep", str(spec), "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and needle in err, err
    assert str(spec) in err
    assert not out.exists()
