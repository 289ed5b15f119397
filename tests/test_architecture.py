"""The code's structure as rules: dependencies flow one way (kernel ← sim ← recorder ← pretrain ← rl ← evaluation
← verbs), no import cycles, no other module's private names, first-party imports at module top (a lazy one says
why in a ``# lazy:`` comment). See docs/architecture.md."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("pipeline", "sim", "recorder", "pretrain", "rl", "evaluation")
LAYER = {"pipeline.core": 0, "sim": 1, "recorder": 2, "pretrain": 3, "rl": 4, "evaluation": 5, "pipeline": 6}


def layer(module: str) -> int:
    if module == "pipeline.core" or module.startswith("pipeline.core."):
        return LAYER["pipeline.core"]
    return LAYER[module.split(".")[0]]


def first_party_imports() -> list[tuple[str, str, list[str], bool, str]]:
    """(importer, imported module, names, at module top, source line) of every first-party import."""
    out = []
    for path in sorted(p for pkg in PACKAGES for p in (ROOT / pkg).rglob("*.py")):
        module = ".".join(path.relative_to(ROOT).with_suffix("").parts).removesuffix(".__init__")
        text = path.read_text()
        tree = ast.parse(text)
        top = {id(n) for n in tree.body}
        lines = text.splitlines()
        for node in ast.walk(tree):
            if isinstance(node, ast.ImportFrom) and node.module and node.module.split(".")[0] in PACKAGES:
                target, names = node.module, [a.name for a in node.names]
            elif isinstance(node, ast.Import) and node.names[0].name.split(".")[0] in PACKAGES:
                target, names = node.names[0].name, []
            else:
                continue
            out.append((module, target, names, id(node) in top, lines[node.end_lineno - 1]))
    return out


IMPORTS = first_party_imports()


def test_the_scan_sees_the_code():
    assert len({i[0] for i in IMPORTS}) > 80 and any(i[1] == "pipeline.core.errors" for i in IMPORTS)


def test_dependencies_flow_one_way():
    back = [(a, b) for a, b, *_ in IMPORTS if layer(b) > layer(a)]
    assert not back, f"imports against the layer order: {back}"


def test_no_import_cycles():
    graph: dict[str, set[str]] = {}
    for a, b, *_ in IMPORTS:
        graph.setdefault(a, set()).add(b)
    state: dict[str, int] = {}
    stack: list[str] = []

    def visit(v: str) -> list[str] | None:
        state[v] = 1
        stack.append(v)
        for w in graph.get(v, ()):
            if w not in graph:
                continue
            if state.get(w) == 1:
                return stack[stack.index(w):] + [w]
            if w not in state and (cycle := visit(w)):
                return cycle
        state[v] = 2
        stack.pop()
        return None

    for v in sorted(graph):
        if v not in state and (cycle := visit(v)):
            pytest.fail(f"import cycle: {' -> '.join(cycle)}")


def test_no_private_names_across_modules():
    private = [(a, b, n) for a, b, names, *_ in IMPORTS for n in names if n.startswith("_")]
    assert not private, f"private names imported from another module: {private}"


def test_first_party_imports_are_at_module_top_or_say_why():
    hidden = [(a, b) for a, b, _, top, line in IMPORTS if not top and "# lazy:" not in line]
    assert not hidden, f"first-party imports inside functions without a '# lazy: <why>' comment: {hidden}"


# Modules whose import takes seconds and that only some code paths need: figures (matplotlib), statistics
# (scipy.stats) and the ResNet trunk (torchvision, which pulls in torch._dynamo). Every fresh process pays for what
# its entry module imports — a Ray worker, a spawned pool, a child of train-all, the CLI — so the modules such
# processes start from import them lazily (docs/results.md, Performance: process start-up).
HEAVY = ("torchvision", "matplotlib", "scipy.stats")
WORKER_ENTRIES = ("rl.dagger", "evaluation.harness", "pipeline.verbs.train", "pipeline.verbs.pretrain",
                  "pipeline.verbs.pretrain_intention", "pipeline.verbs.record", "pipeline.verbs.export")


def test_worker_entry_modules_leave_the_heavy_imports_to_the_code_that_needs_them():
    import subprocess
    import sys

    code = ("import importlib, sys\n"
            f"for m in {WORKER_ENTRIES!r}: importlib.import_module(m)\n"
            f"print('heavy:' + ','.join(h for h in {HEAVY!r} if h in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr[-2000:]
    loaded = [ln.removeprefix("heavy:") for ln in out.stdout.splitlines() if ln.startswith("heavy:")]
    assert loaded == [""], f"imported at module level: {loaded}"
