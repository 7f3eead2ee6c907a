"""The project's modules in layers that import one way, and public names across modules (issue 32).

:data:`LAYERS` puts every module of ``benchmark`` and ``priors`` in a layer, lowest first (the table
of docs/architecture.md, "Packages and layers"); :data:`MAY_IMPORT` says which layers a layer may
import: its own and those below it, except that the priors import only the core (they receive
their training data as arguments). Imports are read with :mod:`ast`, at module level and inside
functions alike (a deferred import is still a dependency). One exception is named: the ``main``
function of a prior's ``train.py`` is the recipe's command line (``python -m priors.NAME.train``), a
command; it builds the training data and hands it to the recipe.

Besides: no import loop between packages (a sub-package, a top-level module, or a module of a
layer's package such as ``benchmark.core.motion``, as one node); the
harness imports only the prior API of ``priors`` (the rest it reaches through
:mod:`benchmark.run.registry`); a prior's network imports no training code; no module imports an
underscore name of another module (``from m import _x`` or ``m._x``); no module re-exports a name
it only imports, and every ``from m import x`` (tests included) takes x from the module that
defines it (package ``__init__`` files, a package's public face, excepted).
"""

from __future__ import annotations

import ast
from pathlib import Path

from test_import_cycles import ROOT, find_cycle, project_modules

# Layer -> module names; "pkg.*" stands for a package and every module of it not named elsewhere (an
# exact name wins over a pattern, a longer pattern over a shorter one).
LAYERS: dict[str, tuple[str, ...]] = {
    # conventions and pure functions: the skeleton, rotations, frames, interpolation, the Motion
    # type, body models, metrics, and small utilities every layer shares (input checks, safe
    # loading, argument types, signals, output folders, provenance, fit diagnostics, canonical JSON
    # and atomic files, the work unit and its result: what the protocols and the runner exchange)
    "core": ("benchmark", "benchmark.core.*", "benchmark.body.*", "benchmark.metrics.*", "benchmark.tables"),
    # data: observations synthesised from motions, their degradation, loaders, the synthetic
    # generator and its splits, a table's test motions, the arrays a unit keeps
    "data": ("benchmark.data.*", "benchmark.loaders.*", "benchmark.synthetic.*"),
    # the priors: the adapter API, the shared training recipe, one package per prior
    "priors": ("priors", "priors.*"),
    # the rules of each table: one protocol module per table, the completion fit and its parts
    "protocols": ("benchmark.protocols.*",),
    # running a table: the runner and its backends, derivation, writing, the prior registry, the
    # catalog of specs and profiles; the HTML report; the library code behind some commands (tools)
    "run": ("benchmark.run.*", "benchmark.tools.*", "benchmark.report.*"),
    # the command line: one module per command, the parser and main
    "commands": ("benchmark.__main__", "benchmark.cli", "benchmark.commands.*"),
}
ORDER = tuple(LAYERS)
MAY_IMPORT = {
    "core": {"core"},
    "data": {"core", "data"},
    "priors": {"core", "priors"},
    "protocols": {"core", "data", "priors", "protocols"},
    "run": {"core", "data", "priors", "protocols", "run"},
    "commands": set(ORDER),
}
# what the harness (benchmark.*) may import of priors: the adapter API, the prior-free start of the
# fits, the training helpers and resumable state of the `train` command; every prior itself through
# benchmark.run.registry
HARNESS_MAY_IMPORT_PRIORS = {"priors.base", "priors.no_prior", "priors.training", "priors.training_state"}
# functions that are a command although their module is not: a recipe's command line
ENTRY_POINTS = {"main"}


def layer_of(module: str) -> str:
    exact = [layer for layer, names in LAYERS.items() if module in names]
    if exact:
        assert len(exact) == 1, f"{module} is named in layers {exact}"
        return exact[0]
    best, best_len = None, -1
    for layer, names in LAYERS.items():
        for pattern in names:
            if (pattern.endswith(".*") and (module + ".").startswith(pattern[:-1])
                    and len(pattern) > best_len):
                best, best_len = layer, len(pattern)
    if best is None:
        raise KeyError(f"{module} has no layer: add it to LAYERS in tests/test_layers.py and to docs/architecture.md")
    return best


def _resolve(name: str, file: Path, node: ast.ImportFrom) -> str:
    if not node.level:
        return node.module or ""
    base = name.split(".") if file.name == "__init__.py" else name.split(".")[:-1]
    base = base[: len(base) - (node.level - 1)]
    return ".".join(base + ([node.module] if node.module else []))


def imports_of(name: str, file: Path, modules: dict) -> list[tuple[str, int, str | None, str | None]]:
    """(imported project module, line, the name taken from it or None, the top-level function the
    import is in or None) for every import of ``file``."""
    tree = ast.parse(file.read_text(), filename=str(file))
    out = []

    def visit(node, func):
        for child in ast.iter_child_nodes(node):
            f = func
            if func is None and isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef)) and node is tree:
                f = child.name
            if isinstance(child, ast.Import):
                for a in child.names:
                    if a.name in modules:
                        out.append((a.name, child.lineno, None, f))
            elif isinstance(child, ast.ImportFrom):
                mod = _resolve(name, file, child)
                for a in child.names:
                    if f"{mod}.{a.name}" in modules:
                        out.append((f"{mod}.{a.name}", child.lineno, None, f))
                    elif mod in modules:
                        out.append((mod, child.lineno, a.name, f))
            visit(child, f)

    visit(tree, None)
    return [o for o in out if o[0] != name]


def _where(file: Path, line: int) -> str:
    return f"{file.relative_to(ROOT)}:{line}"


def test_every_module_has_a_layer():
    modules = project_modules()
    missing = []
    for m in modules:
        try:
            layer_of(m)
        except KeyError:
            missing.append(m)
    assert not missing, f"modules without a layer (add them to LAYERS and docs/architecture.md): {missing}"
    assert layer_of("benchmark.run.table_run") == "run" and layer_of("benchmark.protocols.sls") == "protocols"


def test_imports_follow_the_layers():
    modules = project_modules()
    wrong = []
    for name, file in sorted(modules.items()):
        mine = layer_of(name)
        for dep, line, _, func in imports_of(name, file, modules):
            layer = "commands" if func in ENTRY_POINTS and name.startswith("priors.") and name.endswith(".train") else mine
            theirs = layer_of(dep)
            if theirs not in MAY_IMPORT[layer]:
                wrong.append(f"{_where(file, line)}: {name} ({layer}) imports {dep} ({theirs})")
    assert not wrong, ("imports against the layers (a layer imports only those of MAY_IMPORT; move what both "
                       "need down to the layer that owns it):\n" + "\n".join(wrong))


def test_the_harness_reaches_priors_through_the_registry():
    modules = project_modules()
    wrong = [f"{_where(file, line)}: {name} imports {dep}"
             for name, file in sorted(modules.items()) if name.startswith("benchmark")
             for dep, line, _, _ in imports_of(name, file, modules)
             if dep.startswith("priors") and dep not in HARNESS_MAY_IMPORT_PRIORS]
    assert not wrong, "the harness imports a prior directly (use benchmark.run.registry):\n" + "\n".join(wrong)


def test_a_priors_network_imports_no_training_code():
    """priors/<name>/model.py is the network, pure torch: it imports neither the shared training
    recipe (priors.training) nor a train module (shared constants live in the core, e.g.
    benchmark.core.skeleton.SMPL_LIKE_REST_JOINTS)."""
    modules = project_modules()
    wrong = [f"{_where(file, line)}: {name} imports {dep}"
             for name, file in sorted(modules.items()) if name.startswith("priors.") and name.endswith(".model")
             for dep, line, _, _ in imports_of(name, file, modules)
             if dep in ("priors.training", "priors.training_state") or dep.endswith(".train")]
    assert not wrong, "a network imports training code:\n" + "\n".join(wrong)


# the packages that gather a layer's modules: inside them, a module or a sub-package is a node
LAYER_PACKAGES = {"benchmark.core", "benchmark.data", "benchmark.run", "benchmark.tools", "benchmark.commands"}


def package_of(module: str) -> str:
    """The node of the package graph: a sub-package (``benchmark.protocols``, ``priors.hmvae``,
    ``benchmark.run.backends``), a top-level module (``priors.training``) or a module of a layer's
    package (``benchmark.core.motion``)."""
    parts = module.split(".")
    node = ".".join(parts[:2])
    return ".".join(parts[:3]) if node in LAYER_PACKAGES else node


def test_no_import_loop_between_packages():
    modules = project_modules()
    graph: dict[str, set[str]] = {}
    for name, file in modules.items():
        src = package_of(name)
        graph.setdefault(src, set()).update(package_of(d) for d, *_ in imports_of(name, file, modules)
                                            if package_of(d) != src)
    cycle = find_cycle(graph)
    assert cycle is None, "import loop between packages: " + " -> ".join(cycle)


def test_no_module_imports_another_modules_private_names():
    """Every name imported across modules is public: ``from m import _x`` and ``m._x`` only inside m."""
    modules = project_modules()
    wrong = []
    for name, file in sorted(modules.items()):
        tree = ast.parse(file.read_text(), filename=str(file))
        aliases = {}
        for node in ast.walk(tree):
            if isinstance(node, ast.Import):
                for a in node.names:
                    if a.name in modules and a.name != name:
                        aliases[a.asname or a.name.split(".")[0]] = a.asname and a.name or a.name.split(".")[0]
            elif isinstance(node, ast.ImportFrom):
                mod = _resolve(name, file, node)
                for a in node.names:
                    if f"{mod}.{a.name}" in modules:
                        aliases[a.asname or a.name] = f"{mod}.{a.name}"
                    elif mod in modules and mod != name and a.name.startswith("_") and not a.name.startswith("__"):
                        wrong.append(f"{_where(file, node.lineno)}: from {mod} import {a.name}")
        for node in ast.walk(tree):
            if isinstance(node, ast.Attribute) and node.attr.startswith("_") and not node.attr.startswith("__"):
                parts, base = [], node.value
                while isinstance(base, ast.Attribute):
                    parts.append(base.attr)
                    base = base.value
                if isinstance(base, ast.Name) and base.id in aliases:
                    target = ".".join([aliases[base.id], *reversed(parts)])
                    if target in modules and target != name:
                        wrong.append(f"{_where(file, node.lineno)}: {target}.{node.attr}")
    assert not wrong, "private names used across modules (make them public):\n" + "\n".join(sorted(set(wrong)))


def test_no_module_reexports_names_it_does_not_use():
    """A name a module imports from another project module is used there: a re-export kept for old
    imports is removed and its callers import from the name's home (package __init__ files excepted)."""
    modules = project_modules()
    wrong = []
    for name, file in sorted(modules.items()):
        if file.name == "__init__.py":
            continue
        tree = ast.parse(file.read_text(), filename=str(file))
        used = {n.id for n in ast.walk(tree) if isinstance(n, ast.Name)}
        for node in ast.walk(tree):
            if isinstance(node, ast.ImportFrom) and _resolve(name, file, node) in modules:
                for a in node.names:
                    bound = a.asname or a.name
                    if a.name != "*" and bound not in used:
                        wrong.append(f"{_where(file, node.lineno)}: {name} imports {a.name} and never uses it")
    assert not wrong, "imported, unused names (re-exports: import them from their home):\n" + "\n".join(wrong)


def test_layer_table_checks():
    """The checker itself: exact names beat patterns, unknown modules are refused."""
    assert layer_of("benchmark.synthetic.splits") == "data" and layer_of("benchmark.core.work_units") == "core"
    assert layer_of("benchmark.commands.report") == "commands" and layer_of("benchmark.report.build") == "run"
    try:
        layer_of("elsewhere.module")
    except KeyError:
        pass
    else:
        raise AssertionError("a module outside the table must have no layer")
    assert package_of("benchmark.protocols.sls") == "benchmark.protocols" and package_of("benchmark.core.motion") == "benchmark.core.motion"
    assert package_of("benchmark.run.backends.local") == "benchmark.run.backends"


def test_the_top_level_holds_packages_and_few_modules():
    """benchmark/ holds the layers' packages and at most 8 modules (``__init__``, ``__main__``,
    ``cli``): a new module goes into the package of its layer."""
    top = sorted(f.stem for f in (ROOT / "benchmark").glob("*.py"))
    assert len(top) <= 8 and {"__init__", "__main__", "cli"} <= set(top), top
    layers = {layer_of(f"benchmark.{d.name}") for d in (ROOT / "benchmark").iterdir() if (d / "__init__.py").is_file()}
    assert layers == set(ORDER) - {"priors"}, layers


def test_every_parser_is_in_the_commands_package():
    """Every ``add_parser`` call of the harness lives in benchmark/commands/ (one module per command)."""
    wrong = []
    for name, file in sorted(project_modules().items()):
        if not name.startswith("benchmark.") or name.startswith("benchmark.commands."):
            continue
        for node in ast.walk(ast.parse(file.read_text(), filename=str(file))):
            if isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute) and node.func.attr == "add_parser":
                wrong.append(_where(file, node.lineno))
    assert not wrong, "add_parser outside benchmark/commands/:\n" + "\n".join(wrong)


def defined_names(file: Path) -> tuple[set[str], dict[str, str]]:
    """Names a module binds itself at module level (def, class, assignment, also inside module-level
    if / try / with blocks), and the names it imports (name -> where from)."""
    tree = ast.parse(file.read_text(), filename=str(file))
    own: set[str] = set()
    imported: dict[str, str] = {}

    def targets(t):
        if isinstance(t, ast.Name):
            own.add(t.id)
        elif isinstance(t, (ast.Tuple, ast.List)):
            for e in t.elts:
                targets(e)
        elif isinstance(t, ast.Starred):
            targets(t.value)

    def visit(body):
        for st in body:
            if isinstance(st, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
                own.add(st.name)
            elif isinstance(st, ast.Assign):
                for t in st.targets:
                    targets(t)
            elif isinstance(st, (ast.AnnAssign, ast.AugAssign)):
                targets(st.target)
            elif isinstance(st, ast.ImportFrom):
                for a in st.names:
                    imported[a.asname or a.name] = f"{'.' * st.level}{st.module or ''}"
            elif isinstance(st, ast.Import):
                for a in st.names:
                    imported[a.asname or a.name.split(".")[0]] = a.name
            elif isinstance(st, (ast.If, ast.Try, ast.With, ast.For, ast.While)):
                for field in ("body", "orelse", "finalbody"):
                    visit(getattr(st, field, []))
                for h in getattr(st, "handlers", []):
                    visit(h.body)

    visit(tree.body)
    return own, imported


def test_names_are_imported_from_their_home():
    """``from m import x`` takes x from the module that defines it, not from one that imports it
    (a package's ``__init__`` excepted: it is the package's public face). Checked in the packages
    and the tests."""
    modules = project_modules()
    homes = {name: defined_names(file) for name, file in modules.items()}
    files = dict(modules)
    files.update({f"tests.{f.stem}": f for f in sorted((ROOT / "tests").glob("*.py"))})
    wrong = []
    for name, file in sorted(files.items()):
        tree = ast.parse(file.read_text(), filename=str(file))
        for node in ast.walk(tree):
            if not isinstance(node, ast.ImportFrom):
                continue
            mod = _resolve(name, file, node)
            if mod not in modules or modules[mod].name == "__init__.py":
                continue
            own, imported = homes[mod]
            for a in node.names:
                if a.name == "*" or f"{mod}.{a.name}" in modules or a.name in own:
                    continue
                where = imported.get(a.name, "nowhere")
                wrong.append(f"{_where(file, node.lineno)}: from {mod} import {a.name} (it lives in {where})")
    assert not wrong, "names imported from a module that only imports them (import them from their home):\n" + "\n".join(wrong)
