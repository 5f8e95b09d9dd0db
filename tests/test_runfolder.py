"""Run folders (nerfmeta.runfolder): nothing of the user's is ever replaced, --overwrite builds aside,
one writer per folder, stale locks and orphan temporary files are cleaned, one checkpoint format."""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from nerfmeta.cli import main
from nerfmeta.fit.checkpoint import load_checkpoint
from nerfmeta.fit.loop import FitConfig
from nerfmeta.fit.run import RunConfig, run_fit
from nerfmeta.runfolder import (
    LOCK,
    MARKER,
    RunFolderError,
    check_target,
    foreign_entries,
    is_run_of,
    load_checkpoint as load_checkpoint_file,
    open_run,
    run_folder,
)

FAST = ["--iters", "4", "--eval-every", "0", "--renders", "0", "--set", "coarse_iters=0", "--set", "growth_steps=[]",
        "--set", "num_voxels=4096"]


def _config(scene: Path, iters: int = 4, checkpoint_every: int = 2) -> RunConfig:
    return RunConfig(scene=str(scene), model={"coarse_iters": 0, "growth_steps": [], "num_voxels": 4096},
                     fit=FitConfig(iters=iters, batch_rays=64, eval_every=0, checkpoint_every=checkpoint_every), renders=0)


def _tree(root: Path) -> dict[str, bytes]:
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


def _one_error_line(capsys) -> str:
    err = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
    assert len(err) == 1 and "Traceback" not in err[0], err
    return err[0]


# --- --overwrite never deletes what is not ours ------------------------------------------------


def test_overwrite_of_the_scenes_parent_holding_user_files_is_refused(tiny_scene, tmp_path, capsys):
    parent = tmp_path / "p"
    shutil.copytree(tiny_scene, parent / "scene")
    (parent / "thesis.tex").write_text("x\n")
    before = _tree(parent)
    code = main(["fit", str(parent / "scene"), "--out", str(parent), "--init", "scratch", "--overwrite", *FAST])
    assert code == 2
    assert "choose an --out" in _one_error_line(capsys)
    assert _tree(parent) == before


def test_overwrite_of_the_scene_folder_itself_is_refused(tiny_scene, tmp_path, capsys):
    scene = tmp_path / "scene"
    shutil.copytree(tiny_scene, scene)
    before = _tree(scene)
    code = main(["fit", str(scene), "--out", str(scene), "--init", "scratch", "--overwrite", *FAST])
    assert code == 2
    _one_error_line(capsys)
    assert _tree(scene) == before


def test_overwrite_of_a_run_holding_a_user_file_is_refused(tiny_scene, tmp_path, capsys):
    out = tmp_path / "run"
    assert main(["fit", str(tiny_scene), "--out", str(out), *FAST]) == 0
    (out / "notes.txt").write_text("mine")
    capsys.readouterr()
    before = _tree(out)
    assert main(["fit", str(tiny_scene), "--out", str(out), "--overwrite", *FAST]) == 2
    assert "notes.txt" in _one_error_line(capsys)
    assert _tree(out) == before


def test_overwrite_of_a_folder_without_marker_or_run_files_is_refused(tiny_scene, tmp_path, capsys):
    out = tmp_path / "mine"
    out.mkdir()
    (out / "config.json").write_text("{}")  # looks a little like a run, but is not one
    assert main(["fit", str(tiny_scene), "--out", str(out), "--overwrite", *FAST]) == 2
    assert MARKER in _one_error_line(capsys)
    assert (out / "config.json").read_text() == "{}"


def test_overwrite_of_another_kind_of_run_is_refused(tmp_path):
    out = tmp_path / "meta"
    with run_folder(out, "meta") as run:
        (run.dir / "config.json").write_text(json.dumps({"algo": "fomaml"}))
    with pytest.raises(RunFolderError, match="holds a meta-train run"):
        check_target(out, "fit", overwrite=True)


def test_a_run_folder_of_an_older_version_is_recognised(tiny_scene, tmp_path):
    out = tmp_path / "old"
    run_fit(_config(tiny_scene), out)
    (out / MARKER).unlink()  # as written before the marker existed
    (out / LOCK).unlink()
    assert is_run_of(out, "fit") and not is_run_of(out, "meta") and foreign_entries(out, "fit") == []
    run_fit(_config(tiny_scene, iters=3), out, overwrite=True)
    assert json.loads((out / "summary.json").read_text())["iters"] == 3
    assert json.loads((out / MARKER).read_text())["kind"] == "fit"


# --- --overwrite builds aside: a failure keeps the previous run ---------------------------------


class _Boom(Exception):
    pass


def test_overwrite_then_failure_keeps_the_previous_run(tiny_scene, tmp_path):
    out = tmp_path / "run"
    run_fit(_config(tiny_scene), out)
    before = _tree(out)

    def fail_at_3(record, model, state):
        if record.iter == 3:
            raise _Boom

    with pytest.raises(_Boom):
        run_fit(_config(tiny_scene, iters=6), out, overwrite=True, callbacks=[fail_at_3])
    after = _tree(out)
    assert {k: v for k, v in after.items() if k != LOCK} == {k: v for k, v in before.items() if k != LOCK}
    assert [p.name for p in tmp_path.iterdir()] == ["run"]  # the partial new run is gone too


def test_overwrite_replaces_a_run_of_ours(tiny_scene, tmp_path):
    out = tmp_path / "run"
    run_fit(_config(tiny_scene), out)
    run_fit(_config(tiny_scene, iters=6), out, overwrite=True)
    assert json.loads((out / "summary.json").read_text())["iters"] == 6
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run"]


def test_a_failure_before_anything_was_written_leaves_no_folder(tmp_path, capsys):
    out = tmp_path / "run"
    assert main(["fit", str(tmp_path / "nope"), "--out", str(out)]) == 2
    assert not out.exists()


# --- one writer per folder ----------------------------------------------------------------------


def test_a_second_writer_on_the_same_folder_is_refused(tiny_scene, tmp_path, capsys):
    out = tmp_path / "run"
    with run_folder(out, "fit"):
        code = main(["fit", str(tiny_scene), "--out", str(out), *FAST])
        assert code == 2
        assert "in use by another nerfmeta process" in _one_error_line(capsys)
        with pytest.raises(RunFolderError, match="in use"):
            open_run(out, "fit", overwrite=True)
    assert not (out / "config.json").exists()


_HOLD = """
import sys, time
from nerfmeta.runfolder import open_run
run = open_run(sys.argv[1], "fit")
(run.dir / "config.json").write_text('{"scene": "x"}')
(run.dir / "metrics.jsonl").write_text("")
print("locked", flush=True)
time.sleep(60)
"""


def test_a_second_process_is_refused_and_a_killed_ones_lock_is_taken_over(tmp_path):
    out = tmp_path / "run"
    holder = subprocess.Popen([sys.executable, "-c", _HOLD, str(out)], stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "locked"
        with pytest.raises(RunFolderError, match=f"pid {holder.pid}"):
            open_run(out, "fit", overwrite=True)
    finally:
        holder.send_signal(signal.SIGKILL)
        holder.wait()
    assert (out / LOCK).read_text().strip() == str(holder.pid)  # the stale lock file is still there
    run = open_run(out, "fit", resume=True)
    try:
        assert (out / LOCK).read_text().strip() == str(os.getpid())
    finally:
        run.close()


# --- what kills leave behind --------------------------------------------------------------------


def test_orphan_temporary_files_are_cleaned_on_resume(tiny_scene, tmp_path):
    out = tmp_path / "run"
    with pytest.raises(_Boom):
        def fail_at_3(record, model, state):
            if record.iter == 3:
                raise _Boom
        run_fit(_config(tiny_scene, iters=6), out, callbacks=[fail_at_3])
    orphan = out / ".checkpoint.safetensors.ab12_x9z.tmp"
    orphan.write_bytes(b"half a checkpoint")
    (out / "renders").mkdir(exist_ok=True)
    nested = out / "renders" / ".test_000.png.q1w2e3r4.tmp"
    nested.write_bytes(b"half a png")
    run_fit(_config(tiny_scene, iters=6), out, resume=True)
    assert not orphan.exists() and not nested.exists()
    assert json.loads((out / "summary.json").read_text())["iters"] == 6


def test_an_aside_build_left_by_a_killed_process_is_removed(tmp_path):
    out = tmp_path / "run"
    with run_folder(out, "fit") as run:
        (run.dir / "config.json").write_text('{"scene": "x"}')
        (run.dir / "metrics.jsonl").write_text("")
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    stale = tmp_path / f".run.partial-{dead.pid}"
    stale.mkdir()
    (stale / MARKER).write_text(json.dumps({"format": "nerfmeta-run-1", "kind": "fit"}))
    not_ours = tmp_path / f".run.partial-{dead.pid + 1}"
    not_ours.mkdir()  # no marker: not ours, never removed
    with run_folder(out, "fit", overwrite=True) as run:
        (run.dir / "config.json").write_text('{"scene": "y"}')
    assert not stale.exists() and not_ours.exists()


def test_checkpoints_get_the_same_file_mode_as_the_other_files(tiny_scene, tmp_path):
    old = os.umask(0o022)
    try:
        run_fit(_config(tiny_scene), tmp_path / "run")
    finally:
        os.umask(old)
    mode = lambda name: (tmp_path / "run" / name).stat().st_mode & 0o777  # noqa: E731
    assert mode("checkpoint.safetensors") == mode("summary.json") == mode("config.json") == 0o644


# --- one checkpoint format ----------------------------------------------------------------------


def test_fit_and_meta_checkpoints_share_one_format_and_are_told_apart(tiny_scene, tmp_path):
    run_fit(_config(tiny_scene), tmp_path / "run")
    path = tmp_path / "run" / "checkpoint.safetensors"
    ckpt = load_checkpoint_file(path, "fit")
    assert ckpt.state["step"] == 4 and any(k.startswith("optim.") for k in ckpt.tensors)
    assert load_checkpoint(path).state.step == 4
    from pretrain.meta_run import load_meta_checkpoint

    with pytest.raises(RunFolderError, match="a fit checkpoint, not a meta one"):
        load_meta_checkpoint(path)


def test_a_checkpoint_never_holds_non_finite_values(tmp_path):
    from nerfmeta.runfolder import save_checkpoint

    with pytest.raises(FloatingPointError, match="model.w"):
        save_checkpoint(tmp_path / "c.safetensors", "fit", {"model.w": torch.tensor([1.0, float("nan")])}, {})
    assert not any(tmp_path.iterdir())


# --- the other commands that write a folder -----------------------------------------------------


@pytest.mark.parametrize("kind,own", [("collection", "collection.json"), ("classifier", "classifier.json"),
                                      ("category", "init.json"), ("demo", None)])
def test_every_kind_refuses_to_overwrite_a_folder_holding_a_user_file(tmp_path, kind, own):
    out = tmp_path / kind
    with run_folder(out, kind, aside=kind in ("collection", "classifier", "demo")) as run:
        if own:
            (run.dir / own).write_text("{}")
        else:
            (run.dir / "scenes").mkdir()
    check_target(out, kind, overwrite=True)  # ours: may be replaced
    (out / "thesis.tex").write_text("x")
    with pytest.raises(RunFolderError, match="thesis.tex"):
        check_target(out, kind, overwrite=True)


def test_demo_overwrite_keeps_a_user_folder(tmp_path, capsys):
    out = tmp_path / "demo"
    (out / "scenes").mkdir(parents=True)
    (out / "data").mkdir()
    (out / "data" / "x.txt").write_text("mine")
    assert main(["demo", "--out", str(out), "--zoo", "none", "--overwrite"]) == 2
    _one_error_line(capsys)
    assert (out / "data" / "x.txt").read_text() == "mine"


def test_a_run_built_aside_records_its_final_paths(tmp_path):
    out = tmp_path / "demo"
    with run_folder(out, "demo", aside=True) as run:
        built = run.dir
        (run.dir / "scenes").mkdir()
        (run.dir / "scenes" / "config.json").write_text(json.dumps({"scene": str(run.dir / "scenes" / "a"), "n": 1}))
    assert built != out and not built.exists()
    assert json.loads((out / "scenes" / "config.json").read_text()) == {"scene": str(out / "scenes" / "a"), "n": 1}


def test_resume_of_a_folder_that_is_not_a_run_is_refused(tiny_scene, tmp_path, capsys):
    out = tmp_path / "x"
    out.mkdir()
    (out / "a.txt").write_text("mine")
    assert main(["fit", str(tiny_scene), "--out", str(out), "--resume", *FAST]) == 2
    assert "nothing to resume" in _one_error_line(capsys)
    assert sorted(p.name for p in out.iterdir()) == ["a.txt"]


def test_an_out_folder_under_a_file_is_one_line(tiny_scene, tmp_path, capsys):
    (tmp_path / "file").write_text("mine")
    assert main(["fit", str(tiny_scene), "--out", str(tmp_path / "file" / "run"), *FAST]) == 2
    assert "cannot write there" in _one_error_line(capsys)
    assert (tmp_path / "file").read_text() == "mine"


def _limit_file_size(limit: int):
    def apply() -> None:
        import resource

        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # EFBIG from write() instead of a kill
        resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit))
    return apply


def test_a_full_disk_during_overwrite_is_one_line_and_keeps_the_previous_run(tiny_scene, tmp_path):
    out = tmp_path / "run"
    run_fit(_config(tiny_scene), out)
    before = {k: v for k, v in _tree(out).items() if k != LOCK}
    limit = (out / "checkpoint.safetensors").stat().st_size // 2  # config and metrics fit, a checkpoint does not
    env = dict(os.environ, NERFMETA_ZOO="none", PYTHONPATH=str(Path(__file__).resolve().parents[1]))
    proc = subprocess.run([sys.executable, "-m", "nerfmeta", "fit", str(tiny_scene), "--out", str(out), "--overwrite",
                           "--checkpoint-every", "2", *FAST], capture_output=True, text=True, env=env,
                          preexec_fn=_limit_file_size(limit), timeout=300)
    errors = [line for line in proc.stderr.replace("\r", "\n").splitlines() if ": error: " in line]
    assert proc.returncode == 2 and "Traceback" not in proc.stderr, proc.stderr[-2000:]
    assert len(errors) == 1 and "File too large" in errors[0] and "checkpoint.safetensors" in errors[0]
    assert {k: v for k, v in _tree(out).items() if k != LOCK} == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run"]


def test_a_finished_run_is_kept_aside_when_its_folder_was_taken_meanwhile(tmp_path):
    out = tmp_path / "coll"
    with pytest.raises(RunFolderError, match="the new run is left in"):
        with run_folder(out, "collection", aside=True) as run:
            (run.dir / "collection.json").write_text("{}")
            out.mkdir()
            (out / "thesis.tex").write_text("x")  # someone else's file appeared at --out during the run
    assert (out / "thesis.tex").read_text() == "x"
    assert (run.dir / "collection.json").is_file() and run.dir != out


def test_a_dangling_symlink_as_out_is_one_line(tiny_scene, tmp_path, capsys):
    link = tmp_path / "run"
    link.symlink_to(tmp_path / "gone")
    assert main(["fit", str(tiny_scene), "--out", str(link), *FAST]) == 2
    assert "dangling" in _one_error_line(capsys)
    assert link.is_symlink() and not (tmp_path / "gone").exists()
