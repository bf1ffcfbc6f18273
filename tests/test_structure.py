"""Structure checks of the package (issues 15, 27, 38): the layering stays readable as the code grows.

The import graph is read from the source (ast over every file of virus_nerf/), both kinds of
import: module level (run when the module loads) and lazy (inside a function; a cycle hidden in a
function is still a cycle a reader must untangle, and a lazy import still ties the two layers).
Importing `a.b.c` also runs the `__init__` of `a.b`, so an edge into a module is an edge into the
packages above it too (except the importer's own packages, which Python has loaded before it).

- no import cycle between modules, of any length;
- no import cycle between folders (top-level packages and top-level modules), of any length;
- every import goes down the layers of `LAYERS` (docs/architecture.md draws the same table);
- no module imports a command module (`cli.py`, `*/command.py`) except the commands themselves
  and the experiments, which are commands too;
- the robot's engine (`virus_nerf.engine`: the `Mapper`, its model, config, schedule and views)
  reaches, directly or through what it imports, lazy imports included, only the layers below it:
  nothing of the run (`trainer`), the evaluation, `exports`, `mapping` (replay, stream, map-bag),
  the experiments, the simulator, the config files and flags, or any command; and
  `from virus_nerf import Mapper` loads nothing else (checked in a fresh interpreter);
- every package's `__init__` declares `__all__`: the names it re-exports, or else its public
  modules.
"""

from __future__ import annotations

import ast
import importlib
import subprocess
import sys
import types
from collections import deque
from itertools import pairwise
from pathlib import Path

PACKAGE = Path(__file__).resolve().parents[1] / "virus_nerf"
ENGINE = "virus_nerf.engine"

# What the engine may reach (a module of these or the module itself), the command modules
# excepted. Everything else is a layer the engine must not reach, by default: a new folder is
# outside until it is added here on purpose.
ENGINE_MAY_REACH = ("virus_nerf.checks", "virus_nerf.data", "virus_nerf.errors", "virus_nerf.field",
                    "virus_nerf.grid", "virus_nerf.losses", "virus_nerf.maps", "virus_nerf.render",
                    "virus_nerf.sampler", "virus_nerf.scene_box", "virus_nerf.sensors", "virus_nerf.stereo",
                    "virus_nerf.utils")
# the layers the engine must never reach, named so that widening ENGINE_MAY_REACH over one fails
ENGINE_MUST_NOT_REACH = ("virus_nerf.cli", "virus_nerf.config_flags", "virus_nerf.config_io",
                         "virus_nerf.evaluation", "virus_nerf.experiments", "virus_nerf.exports",
                         "virus_nerf.mapping", "virus_nerf.ros2", "virus_nerf.sim", "virus_nerf.trainer")

# The allowed dependency direction: a folder (or top-level module) imports only from lower tiers,
# never from its own tier or above (today each sits one above the highest tier it imports).
LAYERS: tuple[tuple[str, ...], ...] = (
    ("errors", "checks", "scene_box", "sensors", "losses"),  # 0: no import of the package
    ("utils", "config_io", "config_flags"),                  # 1: errors only
    ("data", "maps", "field", "grid"),                       # 2
    ("stereo", "sim", "render"),                             # 3
    ("sampler", "evaluation"),                               # 4
    ("engine",),                                             # 5: the Mapper
    ("trainer",),                                            # 6: the run around the engine
    ("mapping", "exports", "experiments"),                   # 7: users of a run or a Mapper
    ("ros2",),                                               # 8: the live ROS 2 node (mapping's stream)
    ("cli",),                                                # 9
)

# Import cycles still open, each a tuple of modules (or of folders) in cycle order with its reason.
# None today: issue 27 removed the last folder cycle (exports <-> trainer) with maps/extract.py.
KNOWN_MODULE_CYCLES: dict[tuple[str, ...], str] = {}
KNOWN_FOLDER_CYCLES: dict[tuple[str, ...], str] = {}

# Packages whose `__init__` may leave out `__all__` (with the reason): none today.
ALL_PENDING: set[str] = set()


def _modules() -> dict[str, Path]:
    out = {}
    for path in sorted(PACKAGE.rglob("*.py")):
        rel = path.relative_to(PACKAGE.parent).with_suffix("")
        name = ".".join(rel.parts)
        out[name.removesuffix(".__init__")] = path
    return out


def _packages_of(name: str) -> list[str]:
    """`a.b.c` -> [`a`, `a.b`]."""
    parts = name.split(".")
    return [".".join(parts[:i]) for i in range(1, len(parts))]


def _imports(name: str, path: Path, modules: dict[str, Path]) -> dict[str, bool]:
    """Package modules that `path` imports -> True if only lazily (inside a function)."""
    found: dict[str, bool] = {}

    def add(target: str, lazy: bool) -> None:
        for t in [target, *_packages_of(target)]:
            if t in modules and t != name and t not in _packages_of(name):
                found[t] = found.get(t, True) and lazy

    def walk(node: ast.AST, lazy: bool) -> None:
        for child in ast.iter_child_nodes(node):
            inner = lazy or isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda))
            if isinstance(child, ast.Import):
                for a in child.names:
                    add(a.name, inner)
            elif isinstance(child, ast.ImportFrom):
                base = child.module or ""
                if child.level:  # relative: from the importer's package, `level - 1` up
                    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
                    package = ".".join(package.split(".")[: len(package.split(".")) - child.level + 1])
                    base = f"{package}.{base}".rstrip(".")
                for a in child.names:
                    full = f"{base}.{a.name}"
                    add(full if full in modules else base, inner)
            walk(child, inner)

    walk(ast.parse(path.read_text()), False)
    return found


def _graph() -> dict[str, dict[str, bool]]:
    """module -> {imported module: lazy only}."""
    modules = _modules()
    return {name: _imports(name, path, modules) for name, path in modules.items()}


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """One cycle (a path that ends where it starts) per strongly connected component (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    components: list[set[str]] = []

    def connect(v: str) -> None:  # recursion depth <= number of modules (~150)
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in sorted(graph.get(v, ())):
            if w not in index:
                connect(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = set()
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.add(w)
                if w == v:
                    break
            if len(component) > 1:
                components.append(component)

    for v in sorted(graph):
        if v not in index:
            connect(v)
    cycles = []
    for component in components:  # shortest way back to the first node inside its component
        start = min(component)
        came_from: dict[str, str] = {}
        todo = deque([start])
        while todo:
            v = todo.popleft()
            for w in sorted(graph[v] & component):
                if w == start:
                    path = [v]
                    while path[-1] != start:
                        path.append(came_from[path[-1]])
                    cycles.append([start, *reversed(path[:-1]), start])
                    todo.clear()
                    break
                if w not in came_from:
                    came_from[w] = v
                    todo.append(w)
    return sorted(cycles)


def _canonical(cycle: list[str]) -> tuple[str, ...]:
    """A cycle from its smallest node, without the repeated end."""
    nodes = cycle[:-1]
    i = nodes.index(min(nodes))
    return tuple(nodes[i:] + nodes[:i])


def _unit(module: str) -> str | None:
    """The folder (top-level package) or top-level module a module belongs to; None for the root."""
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else None


def _unit_edges() -> dict[tuple[str, str], list[str]]:
    """(folder, folder) -> the module imports that make the edge."""
    edges: dict[tuple[str, str], list[str]] = {}
    for m, deps in _graph().items():
        for d, lazy in deps.items():
            a, b = _unit(m), _unit(d)
            if a and b and a != b:
                edges.setdefault((a, b), []).append(f"{m} -> {d}" + (" (lazy)" if lazy else ""))
    return edges


def _show(cycle: list[str], graph: dict[str, dict[str, bool]]) -> str:
    return " -> ".join(cycle[:1] + [b + (" (lazy)" if graph[a][b] else "") for a, b in pairwise(cycle)])


def test_the_graph_sees_the_imports_it_must():
    """The reader finds module-level, lazy and package-`__init__` edges (else the checks below
    would pass on an empty graph)."""
    graph = _graph()
    assert graph["virus_nerf.trainer.loop"]["virus_nerf.engine.mapper"] is False  # module level
    assert graph["virus_nerf.mapping.replay"]["virus_nerf.engine.mapper"] is True  # in a function
    assert "virus_nerf.evaluation" in graph["virus_nerf.trainer.config"]  # runs evaluation/__init__
    assert "virus_nerf.engine" not in graph["virus_nerf.engine.mapper"]  # its own package: loaded first
    assert sum(map(len, graph.values())) > 500


def test_the_cycle_finder_finds_cycles_of_any_length():
    ring = {f"m{i}": {f"m{(i + 1) % 5}"} for i in range(5)} | {"x": {"m0"}}
    assert _cycles(ring) == [["m0", "m1", "m2", "m3", "m4", "m0"]]
    assert _cycles({"a": {"b"}, "b": {"c"}, "c": set()}) == []
    assert _canonical(["c", "a", "b", "c"]) == ("a", "b", "c")


def test_no_import_cycle_between_modules():
    graph = _graph()
    cycles = _cycles({m: set(deps) for m, deps in graph.items()})
    new = [c for c in cycles if _canonical(c) not in KNOWN_MODULE_CYCLES]
    assert not new, "import cycles between modules:\n" + "\n".join(_show(c, graph) for c in new)


def test_no_import_cycle_between_folders():
    """A folder that imports another is not imported by it, directly or around any loop: the
    layout shows the data flow."""
    edges = _unit_edges()
    graph: dict[str, set[str]] = {}
    for a, b in edges:
        graph.setdefault(a, set()).add(b)
        graph.setdefault(b, set())
    new = [c for c in _cycles(graph) if _canonical(c) not in KNOWN_FOLDER_CYCLES]
    lines = [" -> ".join(c) + "\n    " + "\n    ".join(edges[a, b][0] for a, b in pairwise(c)) for c in new]
    assert not new, "import cycles between folders:\n" + "\n".join(lines)


def test_imports_go_down_the_layers():
    tier = {unit: i for i, units in enumerate(LAYERS) for unit in units}
    units = {_unit(m) for m in _modules()} - {None}
    assert units == set(tier), (f"place each folder in LAYERS (and docs/architecture.md): missing "
                                f"{sorted(units - set(tier))}, gone {sorted(set(tier) - units)}")
    up = [f"{a} (tier {tier[a]}) -> {b} (tier {tier[b]}): {via[0]}"
          for (a, b), via in sorted(_unit_edges().items()) if tier[b] >= tier[a]]
    assert not up, "imports that do not go down the layers:\n" + "\n".join(up)


def _is_command(name: str) -> bool:
    return name == "virus_nerf.cli" or name.endswith(".command")


def test_no_module_imports_a_command_module():
    bad = [(m, d) for m, deps in _graph().items() for d in deps
           if _is_command(d) and not (_is_command(m) or m.startswith("virus_nerf.experiments"))]
    assert not bad, f"modules importing a CLI command module: {bad}"


def _within(name: str, prefixes: tuple[str, ...]) -> bool:
    return any(name == p or name.startswith(p + ".") for p in prefixes)


def _engine_may_load(name: str) -> bool:
    return name == "virus_nerf" or _within(name, (ENGINE,)) or (
        _within(name, ENGINE_MAY_REACH) and not _is_command(name))


def test_the_engine_reaches_only_the_layers_below_it():
    """Everything the engine imports, transitively (lazy imports included), stays out of the
    layers that use it: a robot program gets the engine without the run, its evaluation, the
    exports, the replay and stream, the experiments or the commands."""
    assert not any(_within(m, ENGINE_MAY_REACH) for m in ENGINE_MUST_NOT_REACH)
    graph = _graph()
    came_from: dict[str, str] = {}
    todo = deque(sorted(m for m in graph if _within(m, (ENGINE,))))
    while todo:
        m = todo.popleft()
        for d in sorted(graph[m]):
            if d not in came_from and not _within(d, (ENGINE,)):
                came_from[d] = m
                todo.append(d)
    assert len(came_from) > 30  # it does reach the layers below (sampler, grid, field, maps, ...)

    def chain(m: str) -> str:
        path = [m]
        while path[-1] in came_from:
            path.append(came_from[path[-1]])
        return " <- ".join(path)

    bad = sorted(m for m in came_from if not _engine_may_load(m))
    assert not bad, "the engine reaches the layers around it:\n" + "\n".join(map(chain, bad))


def _loaded_after(statement: str) -> list[str]:
    code = f"import sys\n{statement}\nprint('\\n'.join(sorted(sys.modules)))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    return out.stdout.split()


def test_importing_the_mapper_loads_only_the_engine_and_below():
    """`from virus_nerf import Mapper` (the README's robot example) loads no run, evaluation,
    export, replay, experiment, simulator or command code; `import virus_nerf` loads nothing."""
    assert [m for m in _loaded_after("import virus_nerf") if m.startswith(("virus_nerf.", "torch"))] == []
    loaded = [m for m in _loaded_after("from virus_nerf import Mapper") if m.split(".")[0] == "virus_nerf"]
    assert "virus_nerf.engine.mapper" in loaded
    assert [m for m in loaded if not _engine_may_load(m)] == []


def test_matplotlib_is_imported_when_a_plot_is_drawn_not_before():
    """`evaluate --no-plots`, `train --no-plots` and the plot folders' names import the plots
    module; matplotlib (1.7 s of start-up on 2 cores) waits for the first plot."""
    assert "matplotlib" not in _loaded_after("import virus_nerf.evaluation.plots")
    assert "matplotlib.pyplot" in _loaded_after("from virus_nerf.evaluation.plots import pyplot\npyplot()")


def test_the_commands_and_the_config_load_no_torch():
    """`train --help` and a mistyped flag of `train`, `export`, `map-bag` or `ros2` (one line,
    exit 2) need the config dataclasses and tyro only: torch, scipy, numba and OpenCV (2-4 s of
    start-up on 2 cores) load with the work, not with the flags (D110)."""
    loaded = _loaded_after("import virus_nerf.trainer.command, virus_nerf.exports.command, virus_nerf.mapping.command, "
                           "virus_nerf.ros2.command\nfrom virus_nerf.trainer.config import TrainConfig\nTrainConfig()\n"
                           "virus_nerf.trainer.command.train_flags({}, 'map,exact')")
    assert [m for m in loaded if m.split(".")[0] in ("torch", "scipy", "numba", "cv2", "matplotlib")] == []


def test_public_api_resolves():
    """`from virus_nerf import Mapper, ...` (the README's robot example) works for every name."""
    import virus_nerf

    for name in virus_nerf.__all__:
        assert getattr(virus_nerf, name).__name__ == name


def _declared_all(path: Path) -> tuple[list[str] | None, set[str]]:
    """An `__init__`'s literal `__all__` (None if absent) and the public names it binds."""
    declared, bound = None, set()
    for node in ast.parse(path.read_text()).body:
        if isinstance(node, ast.ImportFrom) and node.module == "__future__":
            continue
        if isinstance(node, (ast.Import, ast.ImportFrom)):
            bound |= {(a.asname or a.name).split(".")[0] for a in node.names}
        elif isinstance(node, (ast.FunctionDef, ast.ClassDef)):
            bound.add(node.name)
        elif isinstance(node, (ast.Assign, ast.AnnAssign)):
            for target in node.targets if isinstance(node, ast.Assign) else [node.target]:
                if isinstance(target, ast.Name) and target.id == "__all__":
                    declared = ast.literal_eval(node.value)
                elif isinstance(target, ast.Name):
                    bound.add(target.id)
    return declared, {b for b in bound if not b.startswith("_")}


def _is_lazy(path: Path) -> bool:
    """An `__init__` with a module `__getattr__`: its names load on first use (PEP 562)."""
    return any(isinstance(n, ast.FunctionDef) and n.name == "__getattr__" for n in ast.parse(path.read_text()).body)


def test_every_package_declares_its_public_names():
    """`__all__` of a package is the names its `__init__` re-exports (eagerly, or on first use
    through a module `__getattr__`: then each must resolve) or, when it re-exports nothing (no
    import cost on `import virus_nerf.x`), its public modules, all of them."""
    missing, wrong = [], []
    for name, path in _modules().items():
        if path.name != "__init__.py" or name == "virus_nerf":  # the root's is lazy: test_public_api_resolves
            continue
        declared, bound = _declared_all(path)
        if declared is None:
            if name not in ALL_PENDING:
                missing.append(name)
            continue
        if _is_lazy(path):  # names loaded on first use (PEP 562): each must resolve
            package = importlib.import_module(name)
            # a name that is also a submodule's resolves to the module once that is imported
            unresolved = [n for n in declared if isinstance(getattr(package, n, None), types.ModuleType | None)]
            if unresolved or bound or len(declared) != len(set(declared)):
                wrong.append(f"{name}: lazy names {unresolved} do not resolve, or it binds {sorted(bound)} eagerly")
            continue
        modules = {p.stem for p in path.parent.glob("*.py") if p.stem != "__init__"} | {
            p.parent.name for p in path.parent.glob("*/__init__.py")}
        expected = bound or {m for m in modules if not m.startswith("_")}
        if len(declared) != len(set(declared)) or set(declared) != expected:
            wrong.append(f"{name}: __all__ {sorted(set(declared) ^ expected)} differ from "
                         f"{'its re-exports' if bound else 'its modules'}")
    assert not missing, f"packages without __all__: {missing}"
    assert not wrong, "\n".join(wrong)


ARCHITECTURE = PACKAGE.parent / "docs" / "architecture.md"


def test_the_architecture_doc_lists_every_module_and_the_layers():
    """docs/architecture.md is drawn from the code: one section per package (`### \\`virus_nerf/x/\\``)
    listing each of its modules (`- \\`name.py\\`: what it does`), no module that does not exist,
    and the tier table of LAYERS."""
    import re

    documented, section, tiers = set(), None, {}
    for line in ARCHITECTURE.read_text().splitlines():
        if m := re.match(r"### `(virus_nerf/[\w/]*)`", line):
            section = m.group(1).rstrip("/")
        elif line.startswith("#"):
            section = None
        elif section and (m := re.match(r"- `(\w+\.py)`", line)):
            documented.add(f"{section}/{m.group(1)}")
        if m := re.match(r"\| (\d+) \| (.*?) \|", line):
            tiers[int(m.group(1))] = tuple(re.findall(r"`(\w+)`", m.group(2)))
    actual = {str(p.relative_to(PACKAGE.parent)) for p in _modules().values()
              if p.name != "__init__.py" or p.parent == PACKAGE}
    gone, unlisted = sorted(documented - actual), sorted(actual - documented)
    assert not gone, f"docs/architecture.md lists modules that do not exist: {gone}"
    assert not unlisted, f"docs/architecture.md does not list: {unlisted}"
    assert {k: set(v) for k, v in tiers.items()} == {k: set(v) for k, v in enumerate(LAYERS)}, \
        "docs/architecture.md's tier table differs from LAYERS"
