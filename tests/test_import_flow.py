"""The house's import rules, read from the source (ast): data flows one way,
``agents.cli -> agents.benchmark -> agents.training -> controllers -> auv_follow_env``, and no
module inside ``agents/`` imports itself back through others (a circle), counting the imports
made inside functions too (a lazy import hides a circle; it does not remove it)."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("auv_follow_env", "controllers", "agents")

#: layer of a module by its longest matching prefix: a module may import only its own layer or below
LAYERS = {"auv_follow_env": 0, "controllers": 1, "agents.training": 2, "agents.benchmark": 3, "agents.cli": 4,
          "agents.train": 4, "agents": 4}


def module_name(path: Path, root: Path) -> str:
    parts = list(path.relative_to(root).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def project_modules(root: Path, packages=PACKAGES) -> dict[str, Path]:
    return {module_name(p, root): p for pkg in packages for p in sorted((root / pkg).rglob("*.py"))}


def imports_of(name: str, path: Path, known: set[str]) -> set[str]:
    """The project modules ``name`` imports anywhere in its file (a ``from pkg import x`` names
    the submodule ``pkg.x`` when there is one, else the package ``pkg``)."""
    is_pkg = path.name == "__init__.py"
    base = name if is_pkg else name.rpartition(".")[0]
    out: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
        if isinstance(node, ast.Import):
            targets = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            mod = node.module or ""
            if node.level:
                anchor = base.split(".")[: len(base.split(".")) - (node.level - 1)]
                mod = ".".join(anchor + ([mod] if mod else []))
            targets = [f"{mod}.{a.name}" if f"{mod}.{a.name}" in known else mod for a in node.names]
        else:
            continue
        for t in targets:
            while t and t not in known:  # import a.b.c of a module a.b.c or of its package
                t = t.rpartition(".")[0]
            if t and t != name:
                out.add(t)
    return out


def graph(root: Path, packages=PACKAGES) -> dict[str, set[str]]:
    mods = project_modules(root, packages)
    return {m: imports_of(m, p, set(mods)) for m, p in mods.items()}


def layer(mod: str) -> int:
    best = max((k for k in LAYERS if mod == k or mod.startswith(k + ".")), key=len)
    return LAYERS[best]


def against_flow(g: dict[str, set[str]]) -> list[str]:
    return sorted(f"{a} -> {b}" for a, deps in g.items() for b in deps if layer(b) > layer(a))


def facade_edges(g: dict[str, set[str]]) -> set[tuple[str, str]]:
    """A package's ``__init__`` re-exporting its own submodules: the one edge allowed to point
    down into the package; the submodules must never import the package back."""
    return {(a, b) for a, deps in g.items() for b in deps if b.startswith(a + ".")}


def cycles(g: dict[str, set[str]], within: str = "agents") -> list[list[str]]:
    """Every elementary circle among the modules under ``within`` (Johnson-free: a DFS per
    strongly connected component, returning one circle per component found)."""
    allowed = facade_edges(g)
    nodes = sorted(m for m in g if m == within or m.startswith(within + "."))
    edges = {m: sorted(d for d in g[m] if d in nodes and (m, d) not in allowed) for m in nodes}
    index, low, stack, on, comps, counter = {}, {}, [], set(), [], [0]

    def strong(v: str) -> None:  # Tarjan
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on.add(v)
        for w in edges[v]:
            if w not in index:
                strong(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                comps.append(sorted(comp))

    for v in nodes:
        if v not in index:
            strong(v)
    return comps


def test_checker_finds_a_circle_and_an_arrow_against_the_flow(tmp_path):
    """The checker itself, on a made-up tree: a lazy import closing a circle is found, a
    relative import is resolved, a facade ``__init__`` is not a circle, and controllers
    importing agents is an arrow against the flow."""
    files = {
        "agents/__init__.py": "",
        "agents/benchmark/__init__.py": "from agents.benchmark.a import f\n",
        "agents/benchmark/a.py": "from .b import g\n",
        "agents/benchmark/b.py": "def g():\n    from agents.benchmark import a\n",
        "agents/training/__init__.py": "",
        "agents/training/t.py": "import controllers.c\n",
        "controllers/__init__.py": "",
        "controllers/c.py": "def h():\n    from agents.training import t\n",
        "auv_follow_env/__init__.py": "",
    }
    for rel, text in files.items():
        (tmp_path / rel).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / rel).write_text(text)
    g = graph(tmp_path)
    assert g["agents.benchmark.a"] == {"agents.benchmark.b"}
    assert g["agents.benchmark.b"] == {"agents.benchmark.a"}
    assert cycles(g) == [["agents.benchmark.a", "agents.benchmark.b"]]
    assert against_flow(g) == ["controllers.c -> agents.training.t"]


@pytest.fixture(scope="module")
def project_graph() -> dict[str, set[str]]:
    return graph(ROOT)


def test_no_import_circle_inside_agents(project_graph):
    assert cycles(project_graph) == []


def test_imports_follow_the_flow(project_graph):
    """cli -> benchmark -> training -> controllers -> auv_follow_env, never back."""
    assert against_flow(project_graph) == []


def test_submodules_never_import_their_own_package_facade(project_graph):
    back = sorted(f"{a} -> {b}" for a, deps in project_graph.items() for b in deps
                  if b in ("agents.benchmark", "agents.training") and a.startswith(b + "."))
    assert back == []


def test_the_two_rooms_hold_what_they_should(project_graph):
    """Training never needs the benchmark; the benchmark reaches training only for loading runs
    and for what a sweep trains."""
    training = {m for m in project_graph if m.startswith("agents.training")}
    assert len(training) >= 10 and "agents.training.batched_ppo" in training
    assert all(not d.startswith("agents.benchmark") for m in training for d in project_graph[m])
