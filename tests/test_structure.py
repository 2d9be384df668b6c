"""The package's structure, read from its source: imports run one way (no cycle among the modules of ``vnc_warp/``,
``kernels/`` and ``training/``, counting imports inside functions too), and no test patches a knob of the package
(a module constant): tests pass a ``vnc_warp.tuning.Tuning`` instead."""

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
#: The folders of the one installed namespace (pyproject maps kernels/ and training/ under vnc_warp).
PACKAGES = {"vnc_warp": ROOT / "vnc_warp", "vnc_warp.kernels": ROOT / "kernels", "vnc_warp.training": ROOT / "training"}


def _modules() -> dict[str, Path]:
    out = {}
    for name, folder in PACKAGES.items():
        for p in folder.rglob("*.py"):
            parts = [x for x in p.relative_to(folder).with_suffix("").parts if x != "__init__"]
            out[".".join([name, *parts])] = p
    return out


def _absolute(name: str) -> str:
    """``kernels.x`` and ``training.x`` (the source tree's names) as the installed names."""
    head, _, rest = name.partition(".")
    if head in ("kernels", "training"):
        return f"vnc_warp.{head}" + (f".{rest}" if rest else "")
    return name


def import_graph() -> dict[str, set[str]]:
    """Module -> the package modules it imports (anywhere in its body), by installed name."""
    mods = _modules()
    graph = {}
    for mod, path in mods.items():
        package = mod if path.name == "__init__.py" else mod.rpartition(".")[0]
        targets = []
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.Import):
                targets += [_absolute(a.name) for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                base = node.module or ""
                if node.level:
                    parts = package.split(".")
                    base = ".".join(parts[: len(parts) - node.level + 1] + ([base] if base else []))
                base = _absolute(base)
                targets += [f"{base}.{a.name}" if f"{base}.{a.name}" in mods else base for a in node.names]
        deps = set()
        for t in targets:
            while t not in mods and "." in t:
                t = t.rpartition(".")[0]
            if t in mods and t != mod:
                deps.add(t)
        graph[mod] = deps
    return graph


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one module (each holds a cycle)."""
    index, low, stack, on, found = {}, {}, [], set(), []

    def visit(v):
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for w in graph[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while not comp or comp[-1] != v:
                comp.append(stack.pop())
                on.discard(comp[-1])
            if len(comp) > 1:
                found.append(sorted(comp))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return found


def test_no_import_cycle():
    """No cycle among the package's modules: ``training.model`` <->
    ``training.checkpoint`` and ``operators`` <-> ``torch`` were two on main at 8b29078 (this test found both)."""
    graph = import_graph()
    assert {"vnc_warp.operators", "vnc_warp._engine", "vnc_warp.kernels.vnc_terms", "vnc_warp.training.model"} <= set(
        graph)
    assert "vnc_warp.kernels.vnc_terms" in graph["vnc_warp._engine"]  # the graph sees imports through the namespace
    assert cycles(graph) == []


def test_cycle_detector_finds_a_cycle():
    """The detector itself reports a cycle through function-level imports (the form model <-> checkpoint had)."""
    assert cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
    assert cycles({"a": {"b"}, "b": set()}) == []


def test_layers_run_one_way():
    """kernels import nothing of the library, and the library nothing of training (outside the commands, figures
    and plots, which sit beside and may use it)."""
    graph = import_graph()
    for mod, deps in graph.items():
        if mod.startswith("vnc_warp.kernels"):
            assert all(d.startswith("vnc_warp.kernels") for d in deps), (mod, deps)
        elif not mod.startswith(("vnc_warp.training", "vnc_warp.commands", "vnc_warp.cli")):
            assert not any(d.startswith("vnc_warp.training") for d in deps), (mod, deps)


def test_no_test_patches_a_package_constant():
    """No test assigns or monkeypatches a module-level constant (an UPPER_CASE name) of a module: the engine's
    knobs are a ``Tuning`` passed in."""
    bad = []
    for path in sorted((ROOT / "tests").rglob("test_*.py")):
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute) and node.func.attr == "setattr":
                if len(node.args) >= 2 and isinstance(node.args[1], ast.Constant) and str(node.args[1].value).isupper():
                    bad.append(f"{path.name}:{node.lineno}")
            elif isinstance(node, (ast.Assign, ast.AugAssign)):
                for t in node.targets if isinstance(node, ast.Assign) else [node.target]:
                    if isinstance(t, ast.Attribute) and t.attr.isupper() and isinstance(t.value, ast.Name):
                        bad.append(f"{path.name}:{node.lineno}")
    assert bad == []


def test_readme_equation_table_names_exist():
    """Every name of the README's table "equation -> public function -> kernel file" exists: the public functions
    in the package, each term and kernel as a function of the kernel files (``kernels/vnc_*.py``)."""
    import importlib
    import re

    import vnc_warp as vw

    text = (ROOT / "README.md").read_text()
    start = text.index("| equation | public function |")
    table = text[start:text.index("\n\n", start)].splitlines()
    rows = [[c.strip() for c in line.strip("|").split("|")] for line in table]
    kernels = {n.name for f in (ROOT / "kernels").glob("vnc_*.py") for n in ast.walk(ast.parse(f.read_text()))
               if isinstance(n, ast.FunctionDef)}
    public = 0
    for row in rows[2:]:
        assert len(row) == len(rows[0]), row
        for name in re.findall(r"`([A-Za-z_][\w.]*)`", row[1]):
            head, _, attr = name.rpartition(".")
            if head.startswith("vw."):
                owner = getattr(vw, head[3:])
            else:
                owner = vw if head == "vw" else importlib.import_module(head)
            assert callable(getattr(owner, attr, None)), name
            public += 1
        names = [n for cell in row[2:] for n in re.findall(r"`([A-Za-z_]\w*)`", cell)]
        assert names and all(n in kernels for n in names), [n for n in names if n not in kernels]
    assert public >= 9
