"""Structure checks of the package (issue 15): the layering stays readable as the code grows.

- no import circle between modules (lazy imports inside functions included: a circle hidden in
  a function is still a circle a reader must untangle);
- no module imports a command module (`cli.py`, `*/command.py`) except the commands themselves
  and the experiments, which are commands too;
- the robot's engine (`virus_nerf.engine`: the `Mapper`, its model, config and schedule) reaches
  nothing of the run-folder, evaluation, export, replay, CLI or experiment layers, directly or
  through what it imports, lazy imports included (issue 27 replaced a 400-line cap per file,
  which split files by size rather than by concern, with this check);
- no import circle between folders.
"""

from __future__ import annotations

import ast
from pathlib import Path

PACKAGE = Path(__file__).resolve().parents[1] / "virus_nerf"
ENGINE = "virus_nerf.engine.mapper"
# the layers around the engine: the run folder and its loop, the commands, the experiments
AROUND_THE_ENGINE = ("virus_nerf.trainer.loop", "virus_nerf.trainer.run_folder", "virus_nerf.trainer.train_log",
                     "virus_nerf.trainer.report", "virus_nerf.experiments", "virus_nerf.mapping.replay")


def _modules() -> dict[str, Path]:
    out = {}
    for path in sorted(PACKAGE.rglob("*.py")):
        rel = path.relative_to(PACKAGE.parent).with_suffix("")
        name = ".".join(rel.parts)
        out[name.removesuffix(".__init__")] = path
    return out


def _imports(path: Path, modules: dict[str, Path]) -> set[str]:
    """Package modules imported anywhere in `path` (module level or inside functions)."""
    found = set()
    for node in ast.walk(ast.parse(path.read_text())):
        names = []
        if isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            names = [node.module] + [f"{node.module}.{a.name}" for a in node.names]
        for n in names:
            if n in modules:
                found.add(n)
    return found


def _graph() -> dict[str, set[str]]:
    modules = _modules()
    return {name: _imports(path, modules) - {name} for name, path in modules.items()}


def test_no_import_circle():
    graph = _graph()
    # package __init__ files re-export their modules: an edge into a package is not a cycle source
    graph = {m: {d for d in deps if not (PACKAGE.parent / d.replace(".", "/") / "__init__.py").exists()}
             for m, deps in graph.items()}
    state: dict[str, int] = {}
    cycles = []

    def visit(m: str, stack: list[str]) -> None:
        state[m] = 1
        for d in sorted(graph.get(m, ())):
            if state.get(d) == 1:
                cycles.append(stack[stack.index(d):] + [d])
            elif d not in state:
                visit(d, stack + [d])
        state[m] = 2

    for m in sorted(graph):
        if m not in state:
            visit(m, [m])
    assert not cycles, f"import circles: {cycles}"


def _is_command(name: str) -> bool:
    return name == "virus_nerf.cli" or name.endswith(".command")


def test_no_module_imports_a_command_module():
    bad = [(m, d) for m, deps in _graph().items() for d in deps
           if _is_command(d) and not (_is_command(m) or m.startswith("virus_nerf.experiments"))]
    assert not bad, f"modules importing a CLI command module: {bad}"


def test_the_engine_reaches_no_run_cli_or_experiment_module():
    """Everything `Mapper` imports, transitively (lazy imports included), stays out of the layers
    that use it: a robot program gets the engine without the run folder or the commands."""
    graph = _graph()
    reached, todo = set(), [m for m in graph if m == ENGINE or m.startswith(ENGINE + ".")]
    while todo:
        m = todo.pop()
        for d in graph.get(m, ()):
            if d not in reached:
                reached.add(d)
                todo.append(d)
    bad = sorted(m for m in reached if _is_command(m) or m.startswith(AROUND_THE_ENGINE))
    assert not bad, f"{ENGINE} reaches the layers around it: {bad}"


def test_public_api_resolves():
    """`from virus_nerf import Mapper, ...` (the README's robot example) works for every name."""
    import virus_nerf

    for name in virus_nerf.__all__:
        assert getattr(virus_nerf, name).__name__ == name


# folder-level import cycles still open: none (issue 27 removed the last one, exports <-> trainer,
# with one map-extraction module, maps/extract.py, for `export` and the Mapper's snapshots)
KNOWN_FOLDER_CYCLES: set[frozenset[str]] = set()


def test_no_import_circle_between_folders():
    """A folder (package) that imports another must not be imported by it, directly: the layout
    shows the data flow (data -> sensors -> stereo -> sampler -> grid -> ...)."""
    edges = {(m.split(".")[1], d.split(".")[1]) for m, deps in _graph().items() for d in deps
             if m.count(".") >= 2 and d.count(".") >= 2}
    cycles = {frozenset((a, b)) for a, b in edges if a != b and (b, a) in edges}
    assert cycles <= KNOWN_FOLDER_CYCLES, f"import circles between folders: {sorted(map(sorted, cycles - KNOWN_FOLDER_CYCLES))}"
