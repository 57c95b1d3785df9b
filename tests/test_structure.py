"""The package's shape: no import circle between its modules, no module over 400 lines. Read from the source with `ast`, not by importing it."""

import ast
from pathlib import Path

import pytest

import jaxspring as js

PACKAGE = Path(js.__file__).resolve().parent
MAX_LINES = 400


def _modules() -> dict[str, Path]:
    out = {}
    for path in PACKAGE.rglob("*.py"):
        parts = path.relative_to(PACKAGE.parent).with_suffix("").parts
        name = ".".join(parts[:-1] if parts[-1] == "__init__" else parts)
        out[name] = path
    return out


def _imports(name: str, path: Path, modules: dict) -> set[str]:
    """Every module of the package that `name` imports, anywhere in its body (function-level
    and `TYPE_CHECKING` imports count too: a circle is a circle wherever it is written)."""
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    found = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom):
            base = package.split(".")
            if node.level:
                base = base[: len(base) - (node.level - 1)]
                target = ".".join(base + ([node.module] if node.module else []))
            else:
                target = node.module or ""
            for alias in node.names:
                full = f"{target}.{alias.name}"
                found.add(full if full in modules else target)
        elif isinstance(node, ast.Import):
            found.update(alias.name for alias in node.names)
    return {m for m in found if m in modules and m != name}


def _circles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components of more than one module (Tarjan, iteratively)."""
    index, low, stack, on_stack, circles, counter = {}, {}, [], set(), [], 0
    for root in graph:
        if root in index:
            continue
        work = [(root, iter(sorted(graph[root])))]
        index[root] = low[root] = counter
        counter += 1
        stack.append(root)
        on_stack.add(root)
        while work:
            node, children = work[-1]
            child = next(children, None)
            if child is not None:
                if child not in index:
                    index[child] = low[child] = counter
                    counter += 1
                    stack.append(child)
                    on_stack.add(child)
                    work.append((child, iter(sorted(graph[child]))))
                elif child in on_stack:
                    low[node] = min(low[node], index[child])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[node])
            if low[node] == index[node]:
                component = []
                while True:
                    member = stack.pop()
                    on_stack.discard(member)
                    component.append(member)
                    if member == node:
                        break
                if len(component) > 1:
                    circles.append(sorted(component))
    return circles


def test_the_circle_finder_finds_a_circle():
    graph = {"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}, "e": set()}
    assert _circles(graph) == [["a", "b", "c"]]
    assert _circles({"a": {"b"}, "b": set()}) == []


def test_no_import_circle_inside_the_package():
    modules = _modules()
    graph = {name: _imports(name, path, modules) for name, path in modules.items()}
    assert "jaxspring.fit.loop" in graph["jaxspring.fit"]  # the reader sees relative imports
    assert _circles(graph) == []


@pytest.mark.parametrize("name", sorted(_modules()))
def test_no_module_over_400_lines(name):
    lines = len(_modules()[name].read_text().splitlines())
    assert lines <= MAX_LINES, f"{name}: {lines} lines"


def test_the_fit_loop_is_short_and_every_stage_speaks_one_protocol():
    """`fit_batch` (setup, the loop over the plan's stages) is straight-line code of at most
    150 lines, and every stage object `stage_for` can return has the four methods of the
    stage protocol and says whether a checkpoint after its steps resumes exactly."""
    tree = ast.parse((PACKAGE / "fit" / "loop.py").read_text())
    (fit_batch,) = [n for n in tree.body if isinstance(n, ast.FunctionDef) and n.name == "fit_batch"]
    assert fit_batch.end_lineno - fit_batch.lineno + 1 <= 150
    from jaxspring.fit import stages

    for runner in (stages.OptimiserStage, stages.Retreat, stages.SegmentStates):
        assert all(callable(getattr(runner, m, None)) for m in ("init", "step", "done", "result")), runner
        assert isinstance(runner.checkpoints, bool)
