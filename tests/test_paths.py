"""nerfmeta.paths: output files the user names are checked before any work."""

from __future__ import annotations

from pathlib import Path

import pytest

from nerfmeta.errors import ConfigError
from nerfmeta.paths import check_output_file, write_output_json


def test_writable_places_are_accepted(tmp_path: Path) -> None:
    assert check_output_file(tmp_path / "a.json", option="--x") == tmp_path / "a.json"
    assert check_output_file(tmp_path / "new" / "deeper" / "a.json", option="--x") == tmp_path / "new" / "deeper" / "a.json"
    (tmp_path / "old.json").write_text("{}")
    assert check_output_file(tmp_path / "old.json", option="--x") == tmp_path / "old.json"


def test_a_link_to_a_file_writes_the_file_not_the_link(tmp_path: Path) -> None:
    (tmp_path / "real.json").write_text("{}")
    (tmp_path / "link.json").symlink_to(tmp_path / "real.json")
    target = check_output_file(tmp_path / "link.json", option="--x")
    write_output_json(target, {"a": 1}, option="--x")
    assert (tmp_path / "link.json").is_symlink() and (tmp_path / "real.json").read_text().strip().startswith("{")
    assert '"a": 1' in (tmp_path / "real.json").read_text()


def test_a_path_below_a_link_to_nowhere_is_refused(tmp_path: Path) -> None:
    (tmp_path / "gone").symlink_to(tmp_path / "missing_folder")
    with pytest.raises(ConfigError, match="gone is a symbolic link to a missing target"):
        check_output_file(tmp_path / "gone" / "a.json", option="--x")
