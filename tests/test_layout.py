"""The code's layout rules: product code does not import study code; tests do not import each other."""

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _imports(path: Path) -> list[tuple[str, list[str]]]:
    """(module, names) of every import statement in a file, nested ones included."""
    found = []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.ImportFrom) and node.module:
            found.append((node.module, [alias.name for alias in node.names]))
        elif isinstance(node, ast.Import):
            found.extend((alias.name, []) for alias in node.names)
    return found


def _product_files():
    for path in sorted((ROOT / "ivc").rglob("*.py")):
        parts = path.relative_to(ROOT).parts
        if "studies" not in parts and parts[1] != "cli":
            yield path


def test_product_code_does_not_import_study_code():
    offenders = [f"{path.relative_to(ROOT)}: {module}" for path in _product_files()
                 for module, names in _imports(path)
                 if module.startswith("ivc.predict.studies") or (module == "ivc.predict" and "studies" in names)]
    assert not offenders, offenders


def test_no_test_module_imports_another():
    offenders = [f"{path.name}: {module}" for path in sorted((ROOT / "tests").glob("test_*.py"))
                 for module, _ in _imports(path) if module.startswith("tests.test_")]
    assert not offenders, offenders


def test_no_test_imports_a_private_name():
    offenders = [f"{path.name}: {module}.{name}" for path in sorted((ROOT / "tests").glob("*.py"))
                 for module, names in _imports(path) if module.startswith("ivc")
                 for name in names if name.startswith("_") and not name.startswith("__")]
    assert not offenders, offenders


def test_no_product_module_imports_another_modules_private_name():
    offenders = [f"{path.relative_to(ROOT)}: {module}.{name}" for path in _product_files()
                 for module, names in _imports(path) if module.startswith("ivc")
                 for name in names if name.startswith("_") and not name.startswith("__")]
    assert not offenders, offenders


# --- the stage order (docs/architecture.md) ---------------------------------------------------------------------

#: the stages from the ground up; a module may import its own stage and the stages below it, never one above.
#: Stages on one row are peers and do not import each other.
STAGES = (
    ("rotations", "linalg", "errors", "compiled", "units", "files", "igtl"),
    ("dipole",),
    ("session",),
    ("pose",),
    ("fixtures",),
    ("collect",),
    ("sim",),
    ("table",),
    ("correct",),
    ("lut",),
    ("predict",),
    ("live", "export", "report"),
    ("demo", "warmup", "app"),
    ("cli",),
)
#: modules outside a stage's package that belong to it: ivc.truth is the fixtures' evaluation against the declared
#: cube frame (it reads the cube's declared pose; the fixtures' report and every later stage judge by it)
MEMBERS = {"truth": "fixtures"}
#: the data side (collect, sim) is imported by the data side and the application only, never by the map and
#: correction stages: a table and a correction do not depend on how their data was collected
DATA_SIDE = {"collect": {"sim", "predict", "demo", "warmup", "app", "cli"}, "sim": {"demo", "warmup", "app", "cli"}}
#: the one deliberate import circle: the fitter registry (ivc.lut.fitter registers the built-in fitters, whose
#: modules import the Fitter base and ``register`` from it)
REGISTRY = {"ivc.lut.fitter", "ivc.lut.fit_harmonic", "ivc.lut.fit_poly", "ivc.lut.fit_sources", "ivc.lut.fit_adaptive"}

_RANK = {name: rank for rank, row in enumerate(STAGES) for name in row}


def _module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _is_type_checking(node: ast.AST) -> bool:
    test = node.test if isinstance(node, ast.If) else None
    return (isinstance(test, ast.Name) and test.id == "TYPE_CHECKING") or (
        isinstance(test, ast.Attribute) and test.attr == "TYPE_CHECKING")


def _runtime_imports(tree: ast.AST) -> list[ast.AST]:
    """Every import that runs (module level and inside functions), not those under ``if TYPE_CHECKING:``."""
    found, stack = [], [tree]
    while stack:
        node = stack.pop()
        if isinstance(node, ast.If) and _is_type_checking(node):
            stack.extend(node.orelse)
            continue
        if isinstance(node, ast.Import | ast.ImportFrom):
            found.append(node)
        stack.extend(ast.iter_child_nodes(node))
    return found


def _ivc_modules() -> dict[str, Path]:
    return {_module_name(path): path for path in sorted((ROOT / "ivc").rglob("*.py"))}


def _import_graph() -> dict[str, set[str]]:
    """Module -> the ivc modules it imports (a ``from package import name`` names the submodule when it is one),
    with the package of a module imported from another package (its ``__init__`` runs first)."""
    modules = _ivc_modules()
    graph = {}
    for name, path in modules.items():
        targets = set()
        for node in _runtime_imports(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.Import):
                targets.update(alias.name for alias in node.names if alias.name.startswith("ivc"))
            elif node.level == 0 and node.module and node.module.split(".")[0] == "ivc":
                for alias in node.names:
                    sub = f"{node.module}.{alias.name}"
                    targets.add(sub if sub in modules else node.module)
        # importing ivc.a.b first runs ivc.a's __init__: from another package, that is an import of the package too
        home = ".".join(name.split(".")[:2])
        targets |= {".".join(t.split(".")[:2]) for t in targets if ".".join(t.split(".")[:2]) != home}
        graph[name] = {t for t in targets if t != name and t in modules}
    return graph


def _stage(module: str) -> str | None:
    """The stage of ``ivc.X...`` (X); None for the package's front door ``ivc`` itself."""
    parts = module.split(".")
    return MEMBERS.get(parts[1], parts[1]) if len(parts) > 1 else None


def test_every_module_has_a_stage():
    unknown = sorted({_stage(m) for m in _ivc_modules()} - set(_RANK) - {None})
    assert not unknown, f"place these in STAGES (and docs/architecture.md): {unknown}"


def _order_offenders(graph: dict[str, set[str]]) -> list[str]:
    offenders = []
    for module, targets in graph.items():
        here = _stage(module)
        for target in targets:
            there = _stage(target)
            if here is None or there is None or here == there:
                continue  # the front door loads every stage lazily; a stage imports itself freely
            # one floor's stages may import each other; the circle test keeps them acyclic
            if _RANK[there] > _RANK[here]:
                offenders.append(f"{module} ({here}) imports {target} ({there})")
            elif there in DATA_SIDE and here not in DATA_SIDE[there]:
                offenders.append(f"{module} ({here}) imports the data side: {target}")
    return sorted(offenders)


def test_imports_follow_the_stage_order():
    offenders = _order_offenders(_import_graph())
    assert not offenders, "imports against the stage order (docs/architecture.md):\n" + "\n".join(offenders)


def _circles(graph: dict[str, set[str]]) -> list[set[str]]:
    """The strongly connected components of more than one module (Tarjan)."""
    index, low, stack, on_stack, found = {}, {}, [], set(), []

    def visit(v):
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in graph.get(v, ()):
            if w not in index:
                visit(w)
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
                found.append(component)

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return found


def test_no_import_circle_but_the_registry():
    circles = [sorted(c) for c in _circles(_import_graph()) if c != REGISTRY]
    assert not circles, f"import circles: {circles}"


def test_the_checks_catch_what_they_are_for():
    graph = {"ivc.table.a": {"ivc.correct.b"}, "ivc.correct.b": {"ivc.table.a"}, "ivc.dipole.c": {"ivc.rotations"},
             "ivc.lut.d": {"ivc.sim.e"}, "ivc.sim.e": set(), "ivc.rotations": set()}
    assert _order_offenders(graph) == ["ivc.lut.d (lut) imports the data side: ivc.sim.e",
                                       "ivc.table.a (table) imports ivc.correct.b (correct)"]
    assert _circles(graph) == [{"ivc.table.a", "ivc.correct.b"}]
    assert {"ivc.lut.fitter", "ivc.lut.fit_poly"} <= _circles(_import_graph_of_registry())[0]


def _import_graph_of_registry() -> dict[str, set[str]]:
    graph = _import_graph()
    return {m: graph[m] & REGISTRY for m in REGISTRY}


def test_imports_inside_functions_count_and_type_checking_ones_do_not():
    tree = ast.parse("from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from ivc.cli import x\n"
                     "def f():\n    from ivc.correct import y\n")
    assert sorted(node.module for node in _runtime_imports(tree)) == ["ivc.correct", "typing"]
    assert _stage("ivc.truth") == "fixtures" and _stage("ivc.lut.joint") == "lut" and _stage("ivc") is None
