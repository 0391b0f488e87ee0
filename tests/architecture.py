"""The library's architecture: folder tree, import graph, deferred imports, long functions.

Reads the source with :mod:`ast` (nothing is imported) and prints

* the tree of packages with their modules' line counts;
* the import graph between the library's parts (``assets``, ``models.hands``, ``render``,
  ``sample``, ``train``, ..., and the test world ``hogsa_world``), and any cycle in it;
* every import placed inside a function, with the reason written on its line
  (``# deferred: <reason>``);
* every function and module docstring over the line limit, and repeated parameter lists;
* the rules of :func:`violations`: the runtime imports neither training (``train``), the test
  world (``hogsa_world``) nor the experiments; the stages import only earlier stages.

``python tests/architecture.py [--json OUT]``; ``tests/test_architecture.py`` asserts the rules.
"""

from __future__ import annotations

import argparse
import ast
import json
import re
from collections import defaultdict
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Optional

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = "hogsa_loader"
WORLD = "hogsa_world"
#: What is scanned: the library and the generated test world.
ROOTS = (PACKAGE, WORLD)
#: Parts that are not the runtime library: the command line, training, the test world.
TRAINING = "train"
ENTRY_POINTS = ("cli",)
#: The runtime's stages; a stage imports only itself and earlier ones. Data flows assets ->
#: models -> render -> compose -> sample; the rasterisers sit below the models because the
#: trained models render themselves through them. ``base`` is what every stage may use
#: (errors, extras, system, io, geometry).
STAGES = ("base", "assets", "render", "models", "compose", "sample", "view")
BASE = ("errors", "extras", "system", "io", "geometry", "hogsa_loader")
#: Parts outside the stage flow that users call (fine-tuning's model, ARCTIC integration).
CLIENTS = ("baselines", "integrations")
MAX_FUNCTION_LINES = 80
#: A module docstring says what the module is for and where to start, in at most this many lines.
MAX_MODULE_DOC_LINES = 15
#: Two parameter lists sharing this many names (besides self/cls) count as a repeated list
#: (numba kernels are left out: they take flat arrays by necessity).
REPEATED_PARAMS = 10
_DEFERRED = re.compile(r"#\s*deferred:\s*\S")


@dataclass
class DeferredImport:
    """An import statement inside a function."""

    where: str
    names: list[str]
    reason: Optional[str]


@dataclass
class Structure:
    """What :func:`scan` finds in the package."""

    modules: dict[str, int] = field(default_factory=dict)  #: module path -> lines
    edges: dict[str, list[str]] = field(default_factory=dict)  #: package -> packages it imports at module level
    module_edges: dict[str, list[str]] = field(default_factory=dict)  #: module -> library modules it imports
    deferred_edges: dict[str, list[str]] = field(default_factory=dict)  #: package -> packages imported in functions
    deferred: list[DeferredImport] = field(default_factory=list)
    long_functions: list[tuple[int, str]] = field(default_factory=list)
    long_module_docs: list[tuple[int, str]] = field(default_factory=list)  #: (lines, module path)
    params: dict[str, list[str]] = field(default_factory=dict)  #: function -> parameter names
    cycles: list[list[str]] = field(default_factory=list)


def _module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(parts)


def _top_package(module: str) -> str:
    """The part a module belongs to: ``hogsa_loader.assets.hands.mano`` -> ``models.hands``,
    ``hogsa_loader.sample.export.codec`` -> ``sample.export``, ``hogsa_loader.errors`` ->
    ``errors``, anything of the test world -> ``hogsa_world``."""
    parts = module.split(".")
    if parts[0] != PACKAGE:
        return parts[0]
    if len(parts) > 2 and parts[1] in ("assets", "models", "sample"):
        return ".".join(parts[1:3]) if _is_folder(parts[:3]) else parts[1]
    return parts[1] if len(parts) > 1 else parts[0]


def _is_folder(parts: list[str]) -> bool:
    return (ROOT.joinpath(*parts) / "__init__.py").exists()


def _imported_modules(node: ast.AST, module: str, is_package: bool) -> list[str]:
    if isinstance(node, ast.Import):
        return [a.name for a in node.names]
    assert isinstance(node, ast.ImportFrom)
    if node.level:
        base = module.split(".")[: len(module.split(".")) - node.level + int(is_package)]
        return [".".join(base + ([node.module] if node.module else []))]
    return [node.module or ""]


def _is_compiled_kernel(fn: ast.FunctionDef | ast.AsyncFunctionDef) -> bool:
    """A numba kernel: it takes flat arrays by necessity, so its parameter list is not a design choice."""
    for dec in fn.decorator_list:
        target = dec.func if isinstance(dec, ast.Call) else dec
        name = target.attr if isinstance(target, ast.Attribute) else getattr(target, "id", "")
        if name in ("njit", "jit", "vectorize", "guvectorize", "cfunc", "compile_kernel"):
            return True
    return False


def _scan_file(path: Path, out: Structure) -> None:
    module = _module_name(path)
    lines = path.read_text(encoding="utf-8").splitlines()
    out.modules[str(path.relative_to(ROOT))] = len(lines)
    tree = ast.parse("\n".join(lines), filename=str(path))
    doc = ast.get_docstring(tree, clean=False)
    n_doc = len(doc.strip().splitlines()) if doc else 0
    if n_doc > MAX_MODULE_DOC_LINES:
        out.long_module_docs.append((n_doc, str(path.relative_to(ROOT))))
    package = _top_package(module)
    edges = set(out.edges.get(package, []))
    mod_edges: set[str] = set()

    def visit(node: ast.AST, owner: Optional[str]) -> None:
        for child in ast.iter_child_nodes(node):
            inner = owner
            if isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef)):
                inner = f"{module}.{child.name}" if owner is None else f"{owner}.{child.name}"
                n = child.end_lineno - child.lineno + 1
                if n > MAX_FUNCTION_LINES:
                    out.long_functions.append((n, f"{path.relative_to(ROOT)}:{child.lineno} {child.name}"))
                names = [a.arg for a in child.args.posonlyargs + child.args.args + child.args.kwonlyargs]
                if not _is_compiled_kernel(child):
                    out.params[f"{path.relative_to(ROOT)}:{child.lineno} {child.name}"] = [
                        a for a in names if a not in ("self", "cls")
                    ]
            if isinstance(child, (ast.Import, ast.ImportFrom)):
                names = _imported_modules(child, module, path.name == "__init__.py")
                lib = [n for n in names if n.split(".")[0] in ROOTS or n.split(".")[0] == "experiments"]
                if owner is None:
                    mod_edges.update(lib)
                    edges.update(_top_package(n) for n in lib if _top_package(n) != package)
                else:
                    inner_pkgs = {_top_package(n) for n in lib if _top_package(n) != package}
                    out.deferred_edges[package] = sorted(set(out.deferred_edges.get(package, [])) | inner_pkgs)
                    line = " ".join(lines[child.lineno - 1 : child.end_lineno])
                    m = _DEFERRED.search(line)
                    reason = line[m.start() :].split(":", 1)[1].strip() if m else None
                    out.deferred.append(DeferredImport(f"{path.relative_to(ROOT)}:{child.lineno}", names, reason))
            visit(child, inner)

    visit(tree, None)
    out.edges[package] = sorted(edges)
    out.module_edges[module] = sorted(mod_edges)


def _cycles(edges: dict[str, list[str]]) -> list[list[str]]:
    """Strongly connected components of more than one node (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on: set[str] = set()
    found: list[list[str]] = []

    def strong(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for w in edges.get(v, []):
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
                found.append(sorted(comp))

    for v in sorted(edges):
        if v not in index:
            strong(v)
    return found


def scan(*roots: Path) -> Structure:
    """Scan every ``.py`` file under ``roots`` (default: the library and the test world)."""
    out = Structure()
    for root in roots or tuple(ROOT / r for r in ROOTS):
        for path in sorted(root.rglob("*.py")):
            _scan_file(path, out)
    out.long_functions.sort(reverse=True)
    out.long_module_docs.sort(reverse=True)
    out.cycles = _cycles(out.edges)
    return out


def repeated_parameter_lists(s: Structure) -> list[tuple[str, str, int]]:
    """Pairs of functions sharing at least :data:`REPEATED_PARAMS` parameter names."""
    items = [(k, set(v)) for k, v in s.params.items() if len(v) >= REPEATED_PARAMS]
    pairs = []
    for i, (a, pa) in enumerate(items):
        for b, pb in items[i + 1 :]:
            n = len(pa & pb)
            if n >= REPEATED_PARAMS:
                pairs.append((a, b, n))
    return pairs


def _stage(part: str) -> Optional[str]:
    top = part.split(".")[0]
    if part in BASE or top in BASE:
        return "base"
    return top if top in STAGES else None


def _all_edges(s: Structure) -> dict[str, set[str]]:
    return {p: set(d) | set(s.deferred_edges.get(p, [])) for p, d in s.edges.items()}


def world_importers(s: Structure) -> list[str]:
    """Library parts (not the command line) that import the test world, at module level or
    inside a function."""
    return sorted(p for p, d in _all_edges(s).items() if WORLD in d and p not in ENTRY_POINTS + (WORLD,))


def training_importers(s: Structure) -> list[str]:
    """Runtime parts that import training (only the command line and the test world may)."""
    return sorted(p for p, d in _all_edges(s).items() if TRAINING in d and p not in ENTRY_POINTS + (WORLD,))


def experiment_importers(s: Structure) -> list[str]:
    """Parts of the package that import the experiments (none may: they are outside the wheel)."""
    return sorted(p for p, d in _all_edges(s).items() if "experiments" in d)


def upward_imports(s: Structure) -> list[str]:
    """Module-level imports of a later stage from an earlier one (``render -> sample``)."""
    found = []
    for part, deps in s.edges.items():
        mine = _stage(part)
        if mine is None:
            continue
        for dep in deps:
            theirs = _stage(dep)
            if theirs is not None and STAGES.index(theirs) > STAGES.index(mine):
                found.append(f"{part} -> {dep}")
    return sorted(found)


def violations(s: Structure) -> dict[str, list[str]]:
    """The layering rules: each list is empty when the rule holds."""
    return {
        "library imports the test world": world_importers(s),
        "runtime imports training": training_importers(s),
        "package imports experiments": experiment_importers(s),
        "stage imports a later stage": upward_imports(s),
        "package cycles": [" <-> ".join(c) for c in s.cycles],
        "deferred import without a reason": [d.where for d in s.deferred if not d.reason],
        "pom/srm above gaussians": [
            p for p in ("models.pom", "models.srm") if "models.gaussians" in s.edges.get(p, [])
        ],
        "long module docstring": [where for _, where in s.long_module_docs],
    }


def _tree(s: Structure) -> list[str]:
    folders: dict[str, list[tuple[str, int]]] = defaultdict(list)
    for path, n in s.modules.items():
        folders[str(Path(path).parent)].append((Path(path).name, n))
    rows = []
    for folder in sorted(folders):
        total = sum(n for _, n in folders[folder])
        rows.append(f"{folder}/  ({len(folders[folder])} modules, {total} lines)")
    return rows


def report(s: Structure) -> str:
    """The printed report."""
    out = ["# tree", *_tree(s), "", "# package imports (module level)"]
    out += [f"{p:16s} -> {', '.join(d) or '-'}" for p, d in sorted(s.edges.items())]
    out += ["", f"# imports inside functions: {len(s.deferred)}"]
    out += [f"{d.where}  {', '.join(d.names)}  -- {d.reason or 'NO REASON'}" for d in s.deferred]
    out += ["", f"# functions over {MAX_FUNCTION_LINES} lines: {len(s.long_functions)}"]
    out += [f"{n:4d}  {where}" for n, where in s.long_functions]
    out += ["", f"# module docstrings over {MAX_MODULE_DOC_LINES} lines: {len(s.long_module_docs)}"]
    out += [f"{n:4d}  {where}" for n, where in s.long_module_docs]
    rep = repeated_parameter_lists(s)
    out += ["", f"# repeated parameter lists (>= {REPEATED_PARAMS} shared names): {len(rep)}"]
    out += [f"{a} ~ {b} ({n})" for a, b, n in rep]
    out += ["", "# rules"]
    for rule, found in violations(s).items():
        more = f" (+{len(found) - 8} more)" if len(found) > 8 else ""
        out.append(f"{rule}: {', '.join(found[:8]) + more if found else 'none'}")
    return "\n".join(out)


def main(argv: Optional[list[str]] = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--json", help="also write the figures to this JSON file")
    args = parser.parse_args(argv)
    s = scan()
    print(report(s))
    if args.json:
        data = asdict(s)
        data["repeated_parameter_lists"] = repeated_parameter_lists(s)
        data["violations"] = violations(s)
        Path(args.json).write_text(json.dumps(data, indent=1), encoding="utf-8")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
