"""The README's code blocks, as tests/test_readme.py runs them and .ci/run takes its install and test steps.

Standard library only: ``.ci/run`` calls it before anything is installed
(``python tests/readme.py ci-install`` prints the install block). The rules are in tests/test_readme.py.
"""

from __future__ import annotations

import re
import sys
from dataclasses import dataclass, field
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
DATA = Path(__file__).resolve().parent / "data"
_DIRECTIVE = re.compile(r"^<!--\s*readme-test:\s*(.*?)\s*-->\s*$")


@dataclass
class Block:
    """One fenced code block of the README."""

    lang: str
    line: int  # 1-based line of the first code line
    code: str
    directive: str = ""  # the readme-test comment above it, if any
    replaced: list[tuple[str, str]] = field(default_factory=list)

    @property
    def role(self) -> str:
        return self.directive if self.directive in ("ci-install", "ci-test") else "run"


def readme_blocks(text: str) -> list[Block]:
    """The fenced ``bash``/``python`` blocks of ``text`` with the readme-test comment right above each."""
    blocks, lines, i = [], text.splitlines(), 0
    while i < len(lines):
        m = re.match(r"^```(\w*)\s*$", lines[i])
        if not m or not m.group(1):
            i += 1
            continue
        lang, start = m.group(1), i + 1
        end = start
        while end < len(lines) and lines[end].strip() != "```":
            end += 1
        above = _DIRECTIVE.match(lines[i - 1]) if i > 0 else None
        if lang in ("bash", "python"):
            blocks.append(Block(lang, start + 1, "\n".join(lines[start:end]) + "\n", above.group(1) if above else ""))
        i = end + 1
    return blocks


def small(block: Block) -> str:
    """The block's code with the replacements of its readme-test comment applied."""
    code = block.code
    if block.role != "run" or not block.directive:
        return code
    for pair in block.directive.split(";"):
        old, sep, new = (s.strip() for s in pair.partition("=>"))
        if not sep or not old:
            raise ValueError(f"README.md:{block.line - 1}: readme-test wants 'OLD => NEW; ...', got {pair!r}")
        if old not in code:
            raise ValueError(f"README.md:{block.line - 1}: readme-test replaces {old!r}, which is not in the block "
                             "below it (update the comment with the block)")
        code = code.replace(old, new.replace("{data}", str(DATA)))
    return code


def ci_block(role: str, text: str | None = None) -> str:
    """The code of the README's one block marked ``role`` ("ci-install" or "ci-test")."""
    found = [b for b in readme_blocks(README.read_text() if text is None else text) if b.role == role]
    if len(found) != 1:
        raise ValueError(f"README.md has {len(found)} blocks marked readme-test: {role}, expected one")
    return found[0].code


if __name__ == "__main__":
    if len(sys.argv) != 2 or sys.argv[1] not in ("ci-install", "ci-test"):
        sys.exit("usage: python tests/readme.py ci-install|ci-test")
    sys.stdout.write(ci_block(sys.argv[1]))
