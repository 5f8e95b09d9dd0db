"""The benchmark scripts' scratch folder: absent or empty is taken, anything else refused, nothing deleted."""

from benchlib.workdir import work_folder_error


def test_an_absent_or_empty_folder_is_taken(tmp_path):
    assert work_folder_error(tmp_path / "new") is None
    assert work_folder_error(tmp_path) is None


def test_a_folder_with_a_users_file_is_refused_and_kept(tmp_path):
    kept = tmp_path / "notes.txt"
    kept.write_text("mine")
    error = work_folder_error(tmp_path)
    assert error == f"error: --work {tmp_path}: exists and is not an empty folder; give a new one (nothing is deleted)"
    assert kept.read_text() == "mine"


def test_a_plain_file_is_refused(tmp_path):
    path = tmp_path / "file"
    path.write_text("x")
    assert str(path) in work_folder_error(path, flag="--out")
    assert work_folder_error(path, flag="--out").startswith("error: --out ")
