"""The README runs: every ``bash`` and ``python`` block, in order, in a fresh folder, as a new user would.

How a block is run:

* ``python`` blocks run one after the other in one fresh interpreter (a later block uses what an earlier one
  made), each compiled under the name ``README.md`` with its own line numbers, so a failure points at the
  README line.
* ``bash`` blocks run one after the other with ``bash -euo pipefail`` in the same folder (a later block reads
  what an earlier one wrote: ``meshes/``, ``trajs/``, ``runs/``).
* The line just above a block's opening fence may hold ``<!-- readme-test: OLD => NEW; OLD2 => NEW2 -->``: the
  test replaces each OLD of that block by its NEW (``{data}`` in NEW is this folder's ``data/``), to run a long
  command at a small size on a CPU. Every OLD must be in its block, so a stale replacement fails the test.
* ``<!-- readme-test: ci-install -->`` and ``<!-- readme-test: ci-test -->`` mark the install and test blocks:
  they are CI's own steps (``.ci/run`` runs them verbatim, in a fresh virtual environment), not run here; the
  test checks that there is one of each.

The commands (``vnc-warp``, ``torchrun``, ``python -c``) import this checkout's package: its root is put first on
``PYTHONPATH``, as pytest's own ``pythonpath`` does for the tests.
"""

from __future__ import annotations

import os
import subprocess
import sys

import pytest
from readme import README, ROOT, Block, ci_block, readme_blocks, small


def _env() -> dict:
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(ROOT)] + [p for p in env.get("PYTHONPATH", "").split(os.pathsep) if p])
    env.setdefault("OMP_NUM_THREADS", "1")  # tiny torch models: more threads only oversubscribe a small CPU
    env["PYTHONUNBUFFERED"] = "1"
    return env


def _python_program(blocks: list[Block]) -> str:
    """One script that runs every Python block under README.md's line numbers."""
    parts = ["_g = {'__name__': '__main__'}\n"]
    for b in blocks:
        parts.append(f"print('--- README.md:{b.line}', flush=True)\n"
                     f"exec(compile({chr(10) * (b.line - 1) + small(b)!r}, 'README.md', 'exec'), _g)\n")
    return "".join(parts)


def test_readme_parses_and_marks_the_ci_steps():
    """The README has one install and one test block for CI, Python and bash blocks to run, and every readme-test
    replacement names text that is in its block."""
    blocks = readme_blocks(README.read_text())
    install = ci_block("ci-install")
    assert "pip install" in install and "-e " not in install
    assert ci_block("ci-test").split("#")[0].strip() == "python -m pytest -q"
    run = [b for b in blocks if b.role == "run"]
    assert {b.lang for b in run} == {"bash", "python"}
    for b in run:
        small(b)


def test_readme_parser_applies_and_checks_replacements():
    """A readme-test comment right above a fence is that block's; its replacements apply, a stale one is an
    error; a comment elsewhere, other languages and unmarked blocks are left alone."""
    text = ("x `<!-- readme-test: a => b -->`\n```bash\necho a\n```\n"
            "<!-- readme-test: --stages 32 => --stages 2 -->\n```bash\nvnc-warp flow m --stages 32\n```\n"
            "```text\nnot run\n```\n<!-- readme-test: gone => here -->\n```python\nprint(1)\n```\n")
    b = readme_blocks(text)
    assert [x.lang for x in b] == ["bash", "bash", "python"] and b[0].line == 3
    assert small(b[0]) == "echo a\n" and small(b[1]) == "vnc-warp flow m --stages 2\n"
    with pytest.raises(ValueError, match="gone"):
        small(b[2])


@pytest.fixture(scope="module")
def user_folder(tmp_path_factory):
    """A fresh folder to run the README in (nothing of the checkout's in it)."""
    return tmp_path_factory.mktemp("readme-user")


def test_readme_python_blocks_run(user_folder):
    """Every Python block of the README runs, in order, in one fresh interpreter."""
    blocks = [b for b in readme_blocks(README.read_text()) if b.lang == "python" and b.role == "run"]
    proc = subprocess.run([sys.executable, "-c", _python_program(blocks)], cwd=user_folder, env=_env(),
                          capture_output=True, text=True, timeout=1200)
    assert proc.returncode == 0, f"a README Python block failed:\n{proc.stdout[-4000:]}\n{proc.stderr[-6000:]}"
    assert proc.stdout.count("--- README.md:") == len(blocks)


def test_readme_shell_blocks_run(user_folder):
    """Every bash block of the README (but CI's install and test steps) runs, in order, in one folder: the demo
    as written, the flows, dataset, training, generation, evaluation and experiment at small sizes."""
    blocks = [b for b in readme_blocks(README.read_text()) if b.lang == "bash" and b.role == "run"]
    for b in blocks:
        proc = subprocess.run(["bash", "-euo", "pipefail", "-c", small(b)], cwd=user_folder, env=_env(),
                              capture_output=True, text=True, timeout=1800)
        assert proc.returncode == 0, (f"the bash block at README.md:{b.line} failed:\n{small(b)}\n"
                                      f"{proc.stdout[-4000:]}\n{proc.stderr[-6000:]}")
    # what the blocks promise is there: the demo's figures (plots as PNG and PDF), trajectories, a model, scores
    demo = user_folder / "vnc_demo"
    for name in ("scale_stability", "flow_auc"):
        assert (demo / f"{name}.png").stat().st_size > 0 and (demo / f"{name}.pdf").read_bytes()[:4] == b"%PDF"
    for name in ("curvature_scales", "adaptive_scales", "filmstrip", "comparison"):
        assert (demo / f"{name}.png").stat().st_size > 0
    assert (user_folder / "runs" / "cvae1" / "checkpoints" / "last.pt").is_file()
    assert (user_folder / "data" / "index.json").is_file() and (user_folder / "scores.json").is_file()
    assert (user_folder / "results" / "results.md").is_file()
