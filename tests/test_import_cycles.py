"""No import cycles in ``benchmark`` and ``priors``.

Two checks, both fast:
- statically, the graph of imports between the project's modules has no cycle, counting imports
  inside functions too (deferring an import hides a cycle from Python, not from a reader);
- dynamically, every module imports on its own: one subprocess imports each module after dropping
  every project module from ``sys.modules`` (third-party modules such as torch stay loaded), so each
  module is the entry point of its own import once; a cycle that bites only from one side fails here.
"""

from __future__ import annotations

import ast
import json
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("benchmark", "priors")


def project_modules() -> dict[str, Path]:
    """Dotted module name -> file, for every .py file of the packages."""
    out = {}
    for pkg in PACKAGES:
        for f in sorted((ROOT / pkg).rglob("*.py")):
            parts = list(f.relative_to(ROOT).with_suffix("").parts)
            if parts[-1] == "__init__":
                parts = parts[:-1]
            out[".".join(parts)] = f
    return out


def imported_modules(name: str, file: Path, modules: dict[str, Path]) -> set[str]:
    """Project modules that ``file`` imports anywhere: at module level or inside a function (a
    deferred import is still a dependency: ``cli_run`` -> ``conformance`` -> ``cli_run`` through two
    function-level imports was the cycle of issue 17)."""
    tree = ast.parse(file.read_text(), filename=str(file))
    is_pkg = file.name == "__init__.py"
    found: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found.update(a.name for a in node.names if a.name in modules)
        elif isinstance(node, ast.ImportFrom):
            if node.level:  # relative: from . / .. import
                base = name.split(".") if is_pkg else name.split(".")[:-1]
                base = base[: len(base) - (node.level - 1)]
                mod = ".".join(base + ([node.module] if node.module else []))
            else:
                mod = node.module or ""
            for a in node.names:
                sub = f"{mod}.{a.name}"
                if sub in modules:
                    found.add(sub)  # from package import submodule
                elif mod in modules:
                    found.add(mod)
    found.discard(name)
    return found


def find_cycle(graph: dict[str, set[str]]) -> list[str] | None:
    """One cycle of ``graph`` as a list of modules (first == last), or None."""
    state: dict[str, int] = {}
    stack: list[str] = []

    def dfs(u):
        state[u] = 1
        stack.append(u)
        for v in sorted(graph.get(u, ())):
            if state.get(v) == 1:
                return stack[stack.index(v):] + [v]
            if v not in state:
                cyc = dfs(v)
                if cyc:
                    return cyc
        stack.pop()
        state[u] = 2
        return None

    for u in sorted(graph):
        if u not in state:
            cyc = dfs(u)
            if cyc:
                return cyc
    return None


def test_the_import_graph_has_no_cycle():
    modules = project_modules()
    assert "benchmark.run.registry" in modules and "priors.base" in modules, sorted(modules)[:10]
    graph = {m: imported_modules(m, f, modules) for m, f in modules.items()}
    cycle = find_cycle(graph)
    assert cycle is None, (
        "import cycle between project modules: " + " -> ".join(cycle)
        + ". Move what both need to a module that imports neither (e.g. construction to benchmark.run.registry)."
    )


def test_find_cycle_finds_one():
    """The checker itself: a 3-cycle is found, a DAG is not."""
    assert find_cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}}) == ["a", "b", "c", "a"]
    assert find_cycle({"a": {"b", "c"}, "b": {"c"}, "c": set()}) is None


ISOLATED_IMPORTS = r"""
import importlib, json, sys, traceback
names, packages = json.loads(sys.argv[1]), tuple(json.loads(sys.argv[2]))
failed = {}
for name in names:
    for m in [m for m in sys.modules if m.split(".")[0] in packages]:
        del sys.modules[m]
    try:
        importlib.import_module(name)
    except Exception:
        failed[name] = traceback.format_exc(limit=-3)
print(json.dumps(failed))
"""


def test_every_module_imports_on_its_own():
    names = sorted(m for m in project_modules() if not m.endswith("__main__"))
    proc = subprocess.run([sys.executable, "-c", ISOLATED_IMPORTS, json.dumps(names), json.dumps(PACKAGES)],
                          cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    failed = json.loads(proc.stdout.strip().splitlines()[-1])
    assert not failed, "modules that fail to import on their own:\n" + "\n".join(f"{k}:\n{v}" for k, v in failed.items())


SHAPE = ("__init__", "model", "checkpoint", "adapter", "train")
# what each file of a prior package may import from its own package (anywhere in the file)
MAY_IMPORT = {"model": set(), "checkpoint": {"model"}, "train": {"model", "checkpoint"},
              "adapter": {"model", "checkpoint", "train"}}


def test_every_prior_package_has_the_common_shape_and_layering():
    """priors/<name>/ holds __init__, model, checkpoint, adapter and train (package docstring of
    :mod:`priors`), and inside a package model <- checkpoint <- {train, adapter}: the network never
    imports its file formats, recipe or adapter; train never imports the adapter."""
    modules = project_modules()
    packages = sorted(d.name for d in (ROOT / "priors").iterdir() if (d / "__init__.py").is_file())
    assert {"vposer", "frequency_guided", "sequential_primitives", "motion_dvae", "hmvae", "structured_latent"} <= set(packages)
    for pkg in packages:
        missing = [f for f in SHAPE if not (ROOT / "priors" / pkg / f"{f}.py").is_file()]
        assert not missing, f"priors/{pkg}/ lacks {[f + '.py' for f in missing]} (see the priors package docstring)"
        for part, allowed in MAY_IMPORT.items():
            name = f"priors.{pkg}.{part}"
            own = {m.split(".")[2] for m in imported_modules(name, modules[name], modules)
                   if m.startswith(f"priors.{pkg}.") and m.split(".")[2] in MAY_IMPORT}
            assert own <= allowed, f"{name} imports {sorted(own - allowed)} of its own package; allowed: {sorted(allowed)}"
