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


def test_step_host_bench_counts_the_same_operators_at_any_size(tmp_path):
    """bench.step_host writes positive, finite item / collate / dispatch times, and its operator count at the
    negligible sizes equals that of the full tiny model (the operators do not depend on widths or point counts)."""
    import torch

    from bench.step_host import _small, _step, _top_level_ops, main as step_host
    from bench.train_throughput import bench_config
    from torch.utils.data import default_collate
    from vnc_warp.training.model import build_model
    from vnc_warp.training.synthetic import EllipsoidTrajectories
    from vnc_warp.training.train import open_dataset

    report = step_host(["--device", "cpu", "--tiny", "--items", "4", "--repeats", "2", "--out", str(tmp_path)])
    rows = report["rows"]
    for key in ("item", "collate", "dispatch"):
        assert 0 < rows[key]["ms"] < math.inf, rows[key]
    assert (tmp_path / "step_host.json").is_file()
    config = bench_config(tiny=True)
    d = config.data
    ds = open_dataset(EllipsoidTrajectories(num_shapes=2, num_stages=4, num_surface=d.num_surface,
                                            num_queries=d.num_queries, num_on_surface=d.num_on_surface), config)
    b = default_collate([ds[0]])
    torch.manual_seed(0)
    model = build_model(config.model).train()
    _step(model, b, config).backward()  # first calls do one-time work, as the bench's warm-up steps
    loss, fwd = _top_level_ops(lambda: _step(model, b, config))
    _, bwd = _top_level_ops(loss.backward)
    assert _small(config).model.width < config.model.width
    assert (fwd, bwd) == (rows["ops"]["forward_and_loss"], rows["ops"]["backward"])
