"""nerfmeta.io: reading a run's metrics.jsonl back."""

from pathlib import Path

from nerfmeta.io import read_metrics


def test_read_metrics_stops_at_a_torn_line_and_a_missing_file_is_empty(tmp_path: Path):
    path = tmp_path / "metrics.jsonl"
    assert read_metrics(path) == []
    path.write_text('{"iter": 1, "train_psnr": 10.5}\n{"iter": 2}\n{"iter": 3, "tr\n{"iter": 4}\n')
    assert read_metrics(path) == [{"iter": 1, "train_psnr": 10.5}, {"iter": 2}]
