"""benchlib.sections: a script's BENCHMARKS.md section is replaced in place or appended."""

from pathlib import Path

from benchlib.sections import write_section


def test_section_is_replaced_in_place_and_the_others_are_kept(tmp_path: Path):
    path = tmp_path / "BENCHMARKS.md"
    path.write_text("# Benchmarks\n\n## A\n\nold a\n\n## B\n\nb stays\n")
    write_section(path, "## A", "## A\n\nnew a")
    assert path.read_text() == "# Benchmarks\n\n## A\n\nnew a\n\n## B\n\nb stays\n"
    write_section(path, "## B", "## B\n\nnew b\n")
    assert path.read_text() == "# Benchmarks\n\n## A\n\nnew a\n\n## B\n\nnew b\n"


def test_missing_section_and_missing_file_are_appended(tmp_path: Path):
    path = tmp_path / "BENCHMARKS.md"
    write_section(path, "## A", "## A\n\na")
    write_section(path, "## C", "## C\n\nc")
    assert path.read_text() == "# Benchmarks\n\n## A\n\na\n\n## C\n\nc\n"
    # a heading that only starts like ours is another section
    write_section(path, "## A", "## A\n\na2")
    assert path.read_text() == "# Benchmarks\n\n## A\n\na2\n\n## C\n\nc\n"
