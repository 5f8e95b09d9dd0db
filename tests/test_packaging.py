"""Packaging: setup.cfg lists every package, and a non-editable install ships and finds the model zoo."""

from __future__ import annotations

import configparser
import os
import shutil
import site
import subprocess
import sys
from pathlib import Path

import pytest

from nerfmeta import zoo as zoo_module
from nerfmeta.zoo import MANIFEST, resolve_zoo_path

ROOT = Path(__file__).resolve().parents[1]


def _setup_options() -> configparser.SectionProxy:
    cfg = configparser.ConfigParser()
    cfg.read(ROOT / "setup.cfg", encoding="utf-8")
    return cfg["options"]


def _listed(value: str) -> list[str]:
    return [line.strip() for line in value.strip().splitlines() if line.strip()]


def test_setup_cfg_lists_every_package_and_maps_the_zoo():
    options = _setup_options()
    on_disk = {".".join(p.parent.relative_to(ROOT).parts) for top in ("nerfmeta", "classifier", "pretrain")
               for p in (ROOT / top).rglob("__init__.py")}
    assert set(_listed(options["packages"])) == on_disk | {"nerfmeta.model_zoo"}
    assert _listed(options["package_dir"]) == ["nerfmeta.model_zoo = model_zoo"]
    assert (ROOT / "model_zoo" / MANIFEST).is_file()


def test_the_installed_zoo_comes_before_the_checkout_one(tmp_path: Path, monkeypatch: pytest.MonkeyPatch):
    installed, checkout = tmp_path / "site" / "nerfmeta" / "model_zoo", tmp_path / "model_zoo"
    monkeypatch.setattr(zoo_module, "PACKAGED_ZOOS", (installed, checkout))
    monkeypatch.delenv("NERFMETA_ZOO")
    assert resolve_zoo_path(None) is None
    checkout.mkdir()
    (checkout / MANIFEST).write_text("{}")
    assert resolve_zoo_path(None) == checkout
    installed.mkdir(parents=True)
    assert resolve_zoo_path(None) == checkout  # a folder without a manifest is not a zoo
    (installed / MANIFEST).write_text("{}")
    assert resolve_zoo_path(None) == installed
    monkeypatch.setenv("NERFMETA_ZOO", "none")
    assert resolve_zoo_path(None) is None


SOURCES = ("nerfmeta", "classifier", "pretrain", "model_zoo", "setup.cfg", "pyproject.toml", "README.md")


@pytest.mark.slow
def test_non_editable_install_ships_and_finds_the_model_zoo(tmp_path: Path):
    """``pip install .`` into a fresh venv (no dependencies fetched: they come from this test's own
    environment through a .pth file), then the installed package, run from elsewhere, finds and
    verifies the zoo inside its own install, not the checkout's."""
    src = tmp_path / "src"
    for name in SOURCES:  # a copy: an in-tree build would leave build/ and *.egg-info in the checkout
        copy = shutil.copytree if (ROOT / name).is_dir() else shutil.copy2
        copy(ROOT / name, src / name, **({"ignore": shutil.ignore_patterns("__pycache__")} if copy is shutil.copytree else {}))
    venv = tmp_path / "venv"
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(venv)], check=True)
    python = venv / "bin" / "python"
    venv_site = Path(subprocess.run([python, "-c", "import sysconfig; print(sysconfig.get_path('purelib'))"],
                                    check=True, capture_output=True, text=True).stdout.strip())
    (venv_site / "deps.pth").write_text("\n".join(site.getsitepackages()) + "\n")  # torch, setuptools, ...
    env = {k: v for k, v in os.environ.items() if k not in ("NERFMETA_ZOO", "PYTHONPATH")}
    subprocess.run([sys.executable, "-m", "pip", "--python", str(python), "install", "-q", "--no-deps", "--no-index",
                    "--no-build-isolation", str(src)], check=True, env=env, cwd=tmp_path)
    shutil.rmtree(src)  # the install must not lean on the sources
    check = ("import nerfmeta, nerfmeta.zoo as z; p = z.resolve_zoo_path(None); zoo = z.load_zoo(p); "
             "print(nerfmeta.__file__); print(p); print(len(zoo.entries))")
    out = subprocess.run([python, "-c", check], check=True, capture_output=True, text=True, env=env, cwd=tmp_path)
    package_file, zoo_path, n_entries = out.stdout.split()
    assert Path(package_file).parent == venv_site / "nerfmeta"
    assert Path(zoo_path) == venv_site / "nerfmeta" / "model_zoo"
    assert int(n_entries) > 0
    cli = subprocess.run([venv / "bin" / "nerfmeta", "--help"], capture_output=True, text=True, env=env, cwd=tmp_path)
    assert cli.returncode == 0 and "demo" in cli.stdout
