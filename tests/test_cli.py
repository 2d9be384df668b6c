"""The command line behaves like its neighbours: --version, plain help, one spelling of the common options,
status and warnings as log lines, no Warp CUDA-driver noise on a CPU machine, torch threads as asked."""

import argparse
import json
import os
import re
import subprocess
import sys
import warnings
from pathlib import Path

import pytest
import torch

import vnc_warp as vw
from vnc_warp import cli
from vnc_warp.commands.dataset import trajectory_dirs

ROOT = Path(__file__).resolve().parents[1]


def test_version(capsys):
    """`vnc-warp --version` prints the package version and exits 0."""
    with pytest.raises(SystemExit) as exc:
        cli.main(["--version"])
    assert exc.value.code == 0
    assert capsys.readouterr().out.strip() == f"vnc-warp {vw.__version__}"


def _option_helps(parser: argparse.ArgumentParser) -> dict[str, str]:
    """Option string -> its formatted help text, as ``-h`` prints it."""
    formatter = parser._get_formatter()
    return {a.option_strings[-1]: formatter._expand_help(a) for a in parser._actions if a.option_strings and a.help}


def test_help_is_plain_and_says_each_default_once():
    """No Sphinx markup in any help text; no "(default: None)" or "(default: False)"; no option says its default
    twice; every command has the common options, spelled the same."""
    parser = cli.build_parser()
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    texts = [parser.format_help()]
    for name, p in sub.choices.items():
        texts.append(p.format_help())
        helps = _option_helps(p)
        assert {"--no-progress", "--quiet", "--threads"} <= set(helps), name
        for opt, text in helps.items():
            assert text.lower().count("default") <= 1, (name, opt, text)
            assert "(default: None)" not in text and "(default: False)" not in text, (name, opt, text)
        assert not [o for o in helps if o in ("--quiet", "--silent", "--no-bar")
                    and p._option_string_actions[o].container.title != "common options"], name
    for text in texts:
        assert not re.search(r"``|:(func|mod|class|meth|data):`", text), text


def test_flow_warnings_are_log_lines(tmp_path, capsys):
    """A stage that stops at its iteration cap is reported as one log line on stderr
    ("vnc-warp flow: warning: VNC-Flow stage 1: ..."), not a Python warning with its source line; --quiet keeps
    warnings and drops progress bars. The stage is the last one, so no smoothing fallback runs: its status stays
    ``max_iters``."""
    mesh = tmp_path / "shape.obj"
    vw.random_shape(1, subdivisions=2).save(mesh)
    rc = cli.main(["flow", str(mesh), "--stages", "1", "--max-iters", "3", "--out", str(tmp_path / "t"), "--device",
                   "cpu", "--quiet", "--substage-budget", "1"])
    assert rc == 0
    err = capsys.readouterr().err
    lines = [line for line in err.splitlines() if line.strip()]
    assert any(re.match(r"vnc-warp flow: warning: VNC-Flow stage 1: max_iters after 3 iterations", s) for s in lines), err
    assert "UserWarning" not in err and "warnings.warn" not in err and "it/s" not in err


def test_flow_substage_budget_reaches_the_flow(tmp_path, capsys):
    """``--substage-budget`` is the library's ``substage_budget``: the command's stage files are, bit for bit, those
    of :func:`vnc_warp.flow` called with it (and not those of the default, which flows the stage in 16 sub-stages);
    a value outside (0, 1] is a one-line error."""
    mesh = tmp_path / "shape.obj"
    vw.random_shape(1, subdivisions=2).save(mesh)
    argv = ["flow", str(mesh), "--stages", "2", "--max-iters", "20", "--device", "cpu", "--no-progress"]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        assert cli.main([*argv, "--out", str(tmp_path / "cli"), "--substage-budget", "0.5"]) == 0
        api = vw.flow(str(mesh), stages=2, device="cpu", progress=False, max_iters=20, substage_budget=0.5,
                      out_dir=tmp_path / "api")
        fine = vw.flow(str(mesh), stages=2, device="cpu", progress=False, max_iters=20, out_dir=tmp_path / "fine")
    cli_traj = vw.Trajectory.load(tmp_path / "cli")
    assert [st.sha256 for st in cli_traj.stages] == [st.sha256 for st in api.stages]
    assert cli_traj.stages[-1].sha256 != fine.stages[-1].sha256
    capsys.readouterr()
    assert cli.main([*argv, "--out", str(tmp_path / "bad"), "--substage-budget", "0"]) == 2
    err = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
    assert len(err) == 1 and "substage_budget" in err[0], err


def test_no_cuda_driver_warning_on_a_cpu_machine():
    """Importing the package and computing on the CPU prints nothing to stderr (Warp's native start-up warns
    about a missing CUDA driver unless silenced)."""
    code = ("import vnc_warp as vw; m = vw.icosphere(1); print(float(vw.vnc_soft(m, 0.5, device='cpu')[0].numpy()"
            ".mean()))")
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=300)
    assert proc.returncode == 0, proc.stderr
    assert "CUDA driver" not in proc.stderr and "Warp CUDA warning" not in proc.stderr, proc.stderr
    assert float(proc.stdout.strip()) > 0


def test_threads_option_sets_torch_threads_and_restores_them():
    """--threads N sets torch's CPU threads while a command runs and puts the previous value back; the default
    is between 1 and this process's cores; 0 is refused."""
    before = torch.get_num_threads()
    args = argparse.Namespace(command="train", quiet=False, no_progress=False, threads=1)
    restore = cli.configure(args)
    try:
        assert torch.get_num_threads() == 1
    finally:
        restore()
    assert torch.get_num_threads() == before
    assert 1 <= cli.default_threads() <= len(os.sched_getaffinity(0))
    with pytest.raises(ValueError, match="threads"):
        cli.configure(argparse.Namespace(command="train", quiet=False, no_progress=False, threads=0))


def test_dataset_takes_folders_of_trajectories_and_skips_files(tmp_path, caplog):
    """`vnc-warp dataset trajs/*` (a shell glob with flow-batch's batch.json) and `vnc-warp dataset trajs/` name
    the same trajectories; a missing path or a folder without trajectories is an error naming it."""
    trajs = tmp_path / "trajs"
    for name in ("b", "a"):
        (trajs / name).mkdir(parents=True)
        (trajs / name / "manifest.json").write_text(json.dumps({}))
    (trajs / "batch.json").write_text("{}")
    expect = [str(trajs / "a"), str(trajs / "b")]
    assert trajectory_dirs([str(trajs)]) == expect
    with caplog.at_level("INFO", logger="vnc_warp"):
        assert trajectory_dirs(sorted(str(p) for p in trajs.iterdir())) == expect
    assert "batch.json" in caplog.text
    with pytest.raises(FileNotFoundError, match="nowhere"):
        trajectory_dirs([str(tmp_path / "nowhere")])
    (tmp_path / "empty").mkdir()
    with pytest.raises(FileNotFoundError, match="empty"):
        trajectory_dirs([str(tmp_path / "empty")])
