"""The import graph of dope_hope/ and bench/ (read with ast) against docs/ARCHITECTURE.md:
no circles, no arrow up (or sideways) the layers table, export/ free of inference/, the
package face used by the entry points only, bench/ on the library only."""
from __future__ import annotations

import ast
import re
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parent.parent
PACKAGE = "dope_hope"

# No violation is allowed: each set stays empty (a new entry needs a reason beside it).
ALLOWED_CIRCLES: set[frozenset[str]] = set()
ALLOWED_EXPORT_TO_INFERENCE: set[tuple[str, str]] = set()
ALLOWED_BENCH: set[tuple[str, str]] = set()
ENTRY_POINTS = ("dope_hope.commands", "dope_hope.cli", "dope_hope.__main__")


def layers() -> dict[str, int]:
    """{unit: layer} from the table under "## Layers" in docs/ARCHITECTURE.md (the one place
    the order is written)."""
    text = (REPO / "docs" / "ARCHITECTURE.md").read_text()
    section = text.split("\n## Layers\n", 1)[1].split("\n## ", 1)[0]
    out = {}
    for layer, units in re.findall(r"^\| (\d+) \| (.+?) \|$", section, re.M):
        for unit in units.split(","):
            out[unit.split("(")[0].strip()] = int(layer)
    return out


def _modules() -> dict[str, Path]:
    mods = {}
    for path in sorted((REPO / PACKAGE).rglob("*.py")):
        name = ".".join(path.relative_to(REPO).with_suffix("").parts)
        mods[name.removesuffix(".__init__")] = path
    return mods


MODULES = _modules()


def _imports(path: Path, package: str | None) -> list[tuple[str, list[str], int]]:
    """(absolute module, imported names, line) of every import in a file, nested ones too."""
    out = []
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            out += [(a.name, [], node.lineno) for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                parts = package.split(".")[: len(package.split(".")) - (node.level - 1)]
                base = ".".join(parts + ([base] if base else []))
            out.append((base, [a.name for a in node.names], node.lineno))
    return out


def _owner(name: str) -> str | None:
    """The dope_hope module a dotted name refers to (a module, or a name inside one)."""
    while name and name not in MODULES:
        name = name.rpartition(".")[0]
    return name or None


def _graph() -> dict[str, set[str]]:
    graph: dict[str, set[str]] = {}
    for name, path in MODULES.items():
        package = name if path.name == "__init__.py" else name.rpartition(".")[0]
        deps = set()
        for module, names, _ in _imports(path, package):
            targets = [f"{module}.{n}" if f"{module}.{n}" in MODULES else module for n in names] or [module]
            deps |= {o for o in map(_owner, targets) if o and o != name}
        graph[name] = deps
    return graph


GRAPH = _graph()


def _unit(module: str) -> str:
    return PACKAGE if module == PACKAGE else module.split(".")[1]


def _circles() -> set[frozenset[str]]:
    """Strongly connected components of more than one module (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: set[frozenset[str]] = set()

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in sorted(GRAPH[v]):
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
                found.add(frozenset(component))

    for v in sorted(GRAPH):
        if v not in index:
            visit(v)
    return found


def test_every_unit_has_a_layer():
    units = {_unit(m) for m in MODULES}
    table = layers()
    assert units - set(table) == set(), "units missing from the ARCHITECTURE.md layers table"
    assert set(table) - units == set(), "layers table names units that do not exist"


def test_no_import_circles():
    assert _circles() == ALLOWED_CIRCLES


def test_imports_go_down_the_layers():
    table = layers()
    wrong = sorted(f"{m} (layer {table[_unit(m)]}) -> {d} (layer {table[_unit(d)]})"
                   for m, deps in GRAPH.items() for d in deps
                   if _unit(d) != _unit(m) and table[_unit(d)] >= table[_unit(m)])
    assert wrong == []


def test_export_does_not_import_inference():
    found = {(m, d) for m, deps in GRAPH.items() for d in deps
             if m.startswith("dope_hope.export") and d.startswith("dope_hope.inference")}
    assert found == ALLOWED_EXPORT_TO_INFERENCE


def test_library_modules_do_not_import_the_package_face():
    users = sorted(m for m, deps in GRAPH.items() if PACKAGE in deps
                   and m != PACKAGE and not m.startswith(ENTRY_POINTS))
    assert users == []


def _bench_violations(path: Path) -> set[tuple[str, str]]:
    found = set()
    source = path.read_text()
    for module, names, _ in _imports(path, None):
        if module.startswith("dope_hope.commands") or module.split(".")[0] == "tests":
            found.add((path.name, module))
        if module.startswith(PACKAGE) and any(n.startswith("_") for n in names):
            found.add((path.name, f"{module}: private name"))
        if module.startswith(PACKAGE) and module.rpartition(".")[2].startswith("_") \
                and not module.endswith("__main__"):
            found.add((path.name, f"{module}: private module"))
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Attribute) and node.attr.startswith("_") and not node.attr.startswith("__") \
                and isinstance(node.value, ast.Name) and node.value.id in _library_aliases(path):
            found.add((path.name, f"{node.value.id}.{node.attr}: private name"))
    if re.search(r"sys\.path\.(insert|append)\([^)]*tests", source):
        found.add((path.name, "tests on sys.path"))
    return found


def _library_aliases(path: Path) -> set[str]:
    """Local names bound to dope_hope modules (``import dope_hope.x as y``, ``from dope_hope
    import x``) in a bench script."""
    names = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            names |= {a.asname or a.name.split(".")[0] for a in node.names if a.name.startswith(PACKAGE)}
        elif isinstance(node, ast.ImportFrom) and (node.module or "").startswith(PACKAGE):
            names |= {a.asname or a.name for a in node.names
                      if f"{node.module}.{a.name}" in MODULES}
    return names


def test_bench_uses_the_library_only():
    scripts = sorted((REPO / "bench").glob("*.py")) + sorted((REPO / "tools").glob("*.py"))
    found = set().union(*(_bench_violations(p) for p in scripts))
    assert found == ALLOWED_BENCH


@pytest.mark.parametrize("source, expected", [
    ("from dope_hope.commands.infer import X\n", {("x.py", "dope_hope.commands.infer")}),
    ("from dope_hope.refine.line_search import _sample_depth\n",
     {("x.py", "dope_hope.refine.line_search: private name")}),
    ("import sys\nsys.path.insert(0, 'tests')\nfrom fitted_model import scene\n", {("x.py", "tests on sys.path")}),
    ("from dope_hope.refine import line_search as ls\nls._sample_depth\n",
     {("x.py", "ls._sample_depth: private name")}),
    ("from dope_hope.geometry import cuboid_keypoints\n", set()),
])
def test_the_bench_check_catches_each_kind(tmp_path, source, expected):
    path = tmp_path / "x.py"
    path.write_text(source)
    assert _bench_violations(path) == expected


#: Tests of the repository as a whole or of a capability across packages (named for it).
WHOLE_REPOSITORY_TESTS = {"architecture", "docs", "lint", "readme", "packaging", "e2e_quick", "bench_losses",
                          "multi_object_data", "multi_object_model"}


def _module_names() -> set[str]:
    """``package_module`` names of every module and package of dope_hope (``io_meshes``,
    ``inference``, ``catalog``, ...)."""
    names = set()
    for path in (REPO / "dope_hope").rglob("*.py"):
        parts = list(path.relative_to(REPO / "dope_hope").with_suffix("").parts)
        if parts[-1] == "__init__":
            parts = parts[:-1]
        names.update("_".join(parts[:i]) for i in range(1, len(parts) + 1))
    return names


def test_test_files_follow_the_package_layout():
    """tests/test_<package>_<module>[_<aspect>].py: each test file is named for the module (or
    package) it tests, so a newcomer finds a module's tests by its path (cli: the commands)."""
    modules = _module_names()
    stray = [p.name for p in sorted((REPO / "tests").glob("test_*.py"))
             if p.stem[5:] not in WHOLE_REPOSITORY_TESTS
             and not any(p.stem[5:] == m or p.stem[5:].startswith(m + "_") for m in modules)]
    assert not stray, f"test files named for no module of dope_hope: {stray}"


# ----------------------------------------------------------------------------- names
#: Top-level names that several modules define on purpose: name -> (the package every module
#: defining it lies in, the reason). A new entry needs its reason.
ALLOWED_SHARED_NAMES: dict[str, tuple[str, str]] = {
    "add_arguments": ("dope_hope.commands", "the command protocol: cli.py calls each command module's own"),
    "run": ("dope_hope.commands", "the command protocol: cli.py calls each command module's own"),
}


def top_level_definitions(paths: dict[str, Path]) -> dict[str, list[str]]:
    """{name: modules defining it} of the functions and classes at the top of each module."""
    found: dict[str, list[str]] = {}
    for module, path in paths.items():
        for node in ast.parse(path.read_text()).body:
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
                found.setdefault(node.name, []).append(module)
    return found


def shared_names(paths: dict[str, Path]) -> dict[str, list[str]]:
    """The names two modules or more define (private ones too) beyond :data:`ALLOWED_SHARED_NAMES`."""
    shared = {}
    for name, modules in top_level_definitions(paths).items():
        allowed = ALLOWED_SHARED_NAMES.get(name)
        if len(modules) > 1 and not (allowed and all(m.startswith(allowed[0] + ".") for m in modules)):
            shared[name] = modules
    return shared


def test_top_level_names_are_unique():
    """One name, one contract: no two modules of dope_hope define a function or class of the
    same name (a reader who finds the name knows which one is meant)."""
    assert shared_names(MODULES) == {}


def test_the_name_check_catches_a_shared_name(tmp_path):
    (tmp_path / "a.py").write_text("def load(path):\n    pass\n\n\nclass Run:\n    pass\n")
    (tmp_path / "b.py").write_text("def load(path, unit):\n    pass\n\n\ndef run():\n    pass\n")
    paths = {"dope_hope.io.a": tmp_path / "a.py", "dope_hope.io.b": tmp_path / "b.py"}
    assert shared_names(paths) == {"load": ["dope_hope.io.a", "dope_hope.io.b"]}
    paths["dope_hope.io.c"] = paths.pop("dope_hope.io.b")
    (tmp_path / "a.py").write_text("def run():\n    pass\n")
    assert shared_names(paths) == {"run": ["dope_hope.io.a", "dope_hope.io.c"]}  # outside commands/


# ----------------------------------------------------------------------------- module list
def layout_entries() -> dict[str, str]:
    """{entry: its text} of the dope_hope/ tree in the "## Layout" block of docs/ARCHITECTURE.md:
    each top-level module (``catalog.py``) and package (``io/``) with the lines that describe it."""
    text = (REPO / "docs" / "ARCHITECTURE.md").read_text()
    block = text.split("\n## Layout\n", 1)[1].split("```", 2)[1]
    tree = block.split("\ndope_hope/\n", 1)[1]
    entries: dict[str, str] = {}
    name = None
    for line in tree.splitlines():
        if not line.startswith("  "):
            break  # the package's tree ends at the next top-level line (tests/)
        if line[2] != " ":
            name, _, line = line[2:].partition(" ")
            entries[name] = ""
        entries[name] += " " + line.strip()
    return entries


def unnamed_modules() -> list[str]:
    """The modules of dope_hope that the layout's module list does not name: a top-level module
    without its entry, a package's module whose name its package's entry lacks (as a name:
    followed by its description in brackets, a comma, a colon or a semicolon)."""
    entries = layout_entries()
    missing = []
    for path in sorted((REPO / PACKAGE).rglob("*.py")):
        parts = path.relative_to(REPO / PACKAGE).with_suffix("").parts
        if len(parts) == 1:
            if f"{parts[0]}.py" not in entries:
                missing.append(f"{parts[0]}.py")
        elif parts[-1] != "__init__":
            entry = entries.get(f"{parts[0]}/", "")
            if not re.search(rf"(?<![\w./-]){re.escape(parts[-1])}(?=\s*[(,;:)]|\s*$)", entry):
                missing.append("/".join(parts) + ".py")
    return missing


def test_every_module_is_named_in_the_layout():
    assert unnamed_modules() == [], "modules missing from the module list of docs/ARCHITECTURE.md (## Layout)"


#: The longest a module of the package may be: past it, a module holds more than one job.
MAX_MODULE_LINES = 600


def test_no_module_is_over_the_line_limit():
    long = {str(p.relative_to(REPO)): n for p in sorted((REPO / PACKAGE).rglob("*.py"))
            if (n := len(p.read_text().splitlines())) > MAX_MODULE_LINES}
    assert long == {}, f"modules over {MAX_MODULE_LINES} lines: split them by job"
