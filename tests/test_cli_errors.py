"""The command line refuses bad options in one line on stderr, exit 2, writing nothing (issue 15).

Each case here failed on the hand-written options (a traceback, a crash after writing, a
terabyte allocation, or argparse's whole usage); this file imports only the CLI, so it runs
against any version of it.
"""

from __future__ import annotations

import pytest

from nerfmeta.cli import main


@pytest.mark.parametrize("args,needle", [
    (["--backbone", "nerf", "--set", "lr=abc"], "lr=abc: expected a number"),
    (["--set", "lr_features=inf"], "lr_features=inf: must be a finite number"),
    (["--set", "lr_features=nan"], "must be a finite number"),
    (["--set", "num_voxels=1e12"], "is available on this machine"),
    (["--set", "lr_featurs=0.1"], "did you mean 'lr_features'"),
    (["--iters", "abc"], "error: --iters abc: expected a whole number ("),
    (["--iters", "1.5"], "--iters"),
    (["--time-budget", "inf"], "--time-budget"),
    (["--target-psnr", "nan"], "--target-psnr"),
    (["--batch-rays", "0"], "--batch-rays 0: must be >= 1"),
    (["--renders", "-1"], "--renders"),
    (["--downscale", "0.5"], "--downscale"),
    (["--background", "purple"], "--background"),
    (["--eval-ssim", "yes"], "unrecognized arguments"),
    (["--no-such-option"], "unrecognized arguments: --no-such-option (see 'nerfmeta fit --help')"),
    (["--itres", "3"], "unrecognized arguments: --itres 3; did you mean '--iters'?"),
    (["--preset", "concave", "--backbone", "grid"], "--preset concave is a recipe for --backbone sdf, not --backbone grid"),
    (["--preset", "convex"], "--preset 'convex': unknown preset; choose one of concave"),
    (["--preset", "concave", "--set", "eikonal_ramp=[5000,3500]"], "sdf config eikonal_ramp=(5000, 3500) is not allowed"),
])
def test_bad_fit_options_one_line_exit_2_nothing_written(tiny_scene, tmp_path, capsys, args, needle):
    out = tmp_path / "run"
    code = main(["fit", str(tiny_scene), "--out", str(out), "--init", "scratch", "--iters", "2", *args])
    err = capsys.readouterr().err
    assert code == 2, err
    assert err.count("\n") == 1 and needle in err, err
    assert "Traceback" not in err and "usage:" not in err
    assert not out.exists()


def test_argparse_errors_are_one_line_with_a_pointer_to_help(capsys):
    assert main(["fit"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "required" in err and "(see 'nerfmeta fit --help')" in err
    assert main(["no-such-command"]) == 2
    assert capsys.readouterr().err.count("\n") == 1


def test_every_command_help_lists_its_config_fields(capsys):
    for argv, flags in ((["fit"], ("--iters", "--time-budget", "--batch-rays", "--eval-views", "--chunk-rays", "--no-normalize")),
                        (["meta-train"], ("--inner-steps", "--no-jitter", "--categories", "--eval-tasks")),
                        (["pretrain", "category"], ("--category", "--max-scenes", "--batch-rays")),
                        (["make-collection"], ("--scenes-per-category", "--fov", "--full-sphere", "--supersample", "--max-steps")),
                        (["classifier", "train"], ("--arch", "--time-budget", "--keep-fraction", "--weight-decay")),
                        (["demo"], ("--known", "--unseen", "--resolution", "--eval-every"))):
        with pytest.raises(SystemExit):
            main([*argv, "--help"])
        text = capsys.readouterr().out
        assert all(flag in text for flag in flags), (argv, text)




@pytest.fixture(scope="module")
def collection(tmp_path_factory: pytest.TempPathFactory):
    """2 categories x 3 scenes, 16 px, 3 views: enough for pretraining and meta-training to start."""
    from nerfmeta.collection.generate import CollectionConfig, generate_collection
    from nerfmeta.collection.render import RenderConfig

    out = tmp_path_factory.mktemp("cli_coll") / "coll"
    generate_collection(CollectionConfig(categories=("mug", "vase"), scenes_per_category=3, views=3, test_views=1, resolution=16,
                                         val_fraction=0.0, test_fraction=0.34, render=RenderConfig(supersample=1, max_steps=32)), out)
    return out


@pytest.mark.parametrize("argv,needle", [
    (["pretrain", "category", "{coll}", "--category", "mug", "--iters", "500", "--set", "num_voxels=1e12"], "is available"),
    (["pretrain", "category", "{coll}", "--category", "mug", "--set", "lr_density=inf"], "must be a finite number"),
    (["pretrain", "category", "{coll}", "--category", "mug", "--eval-every", "-1"], "--eval-every"),
    (["meta-train", "{coll}", "--backbone", "grid", "--set", "num_voxels=1e12"], "is available"),
    (["meta-train", "{coll}", "--backbone", "nerf", "--set", "lr=abc"], "lr=abc: expected a number"),
    (["meta-train", "{coll}", "--inner-lr", "nan"], "--inner-lr"),
    (["meta-train", "{coll}", "--algo", "sgd"], "--algo"),
    (["meta-train", "{coll}", "--inner-lr-group", "density=inf"], "--inner-lr-group"),
])
def test_bad_pretrain_and_meta_options_one_line_exit_2_nothing_written(collection, tmp_path, capsys, argv, needle):
    out = tmp_path / "out"
    code = main([a.replace("{coll}", str(collection)) for a in argv] + ["--out", str(out)])
    err = capsys.readouterr().err
    assert code == 2, err
    assert err.count("\n") == 1 and needle in err, err
    assert not out.exists()
