"""The training-throughput benchmark (bench/train_throughput.py) runs end to end on the CPU at the tiny sizes."""

import math

from bench.train_throughput import ROWS, format_table, main


def test_every_row_measures_a_positive_finite_rate(tmp_path):
    """Each row (but the compiled one, whose tracing takes most of a CPU minute) appears once with a positive,
    finite items/s equal to batch / (ms/step), the training rows with finite losses, and the JSON is written."""
    rows = [r for r in ROWS if r != "f_compile"]
    report = main(["--device", "cpu", "--tiny", "--steps", "2", "--warmup", "0", "--only", ",".join(rows),
                   "--out", str(tmp_path)])
    assert [r["variant"] for r in report["rows"]] == rows
    for r in report["rows"]:
        assert "error" not in r, r
        assert 0 < r["items_per_s"] < math.inf, r
        assert math.isclose(r["items_per_s"], r["batch"] / (r["ms_per_step"] / 1e3), rel_tol=1e-9)
        if "loss" in r:
            assert math.isfinite(r["loss"]), r
    assert {r["variant"]: r["batch"] for r in report["rows"]}["g_batch64"] == 2 * report["config"]["batch"]
    assert (tmp_path / "train_throughput.json").is_file()
    assert all(name in format_table(report) for name in rows)
