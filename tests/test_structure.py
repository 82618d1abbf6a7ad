"""The library's structure, read from its source with ``ast`` (no third-party tool): no import
cycles (counting imports inside functions), no private name imported from a sibling module (the
validation helpers of ``fsof_torch._check`` aside), no module over 700 lines, and every public
name of the design's contract importable from ``fsof_torch``."""

from __future__ import annotations

import ast
import importlib
import re
from pathlib import Path


import fsof_torch

PACKAGE = Path(fsof_torch.__file__).resolve().parent
MAX_LINES = 700
DESIGN = Path(__file__).resolve().parents[2] / "shared" / "DESIGN.md"


def module_name(path: Path) -> str:
    parts = path.relative_to(PACKAGE.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


MODULES = {module_name(p): p for p in sorted(PACKAGE.rglob("*.py"))}


def is_package(name: str) -> bool:
    return MODULES[name].name == "__init__.py"


def resolve(importer: str, level: int, target: str | None) -> str:
    """The absolute module name of ``from <level dots><target> import ...`` inside ``importer``."""
    if level == 0:
        return target or ""
    base = importer.split(".")
    if not is_package(importer):
        base = base[:-1]
    base = base[: len(base) - (level - 1)]
    return ".".join(base + ([target] if target else []))


def imports(name: str, source: str | None = None) -> list[tuple[str, list[str], int]]:
    """``(module, imported names, line)`` of every import statement in a module (its file, or
    ``source``), at any depth (function-level imports too), with relative imports resolved."""
    tree = ast.parse(MODULES[name].read_text() if source is None else source)
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found.extend((alias.name, [], node.lineno) for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            found.append((resolve(name, node.level, node.module), [a.name for a in node.names], node.lineno))
    return found


def dependencies(name: str, source: str | None = None) -> set[str]:
    """The library modules a module imports: ``from pkg import sub`` counts as importing the
    submodule ``pkg.sub`` where that is a module, else as importing ``pkg``."""
    deps = set()
    for module, names, _ in imports(name, source):
        if not (module == "fsof_torch" or module.startswith("fsof_torch.")):
            continue
        targets = [f"{module}.{n}" for n in names if f"{module}.{n}" in MODULES]
        if len(targets) < len(names) or not names:
            targets.append(module)
        deps.update(t for t in targets if t in MODULES and t != name)
    return deps


def find_cycle(graph: dict[str, set[str]]) -> list[str] | None:
    """One cycle of a directed graph as a list of nodes (first = last), or None."""
    state: dict[str, int] = {}  # 1: on the current path, 2: finished
    path: list[str] = []

    def visit(node: str) -> list[str] | None:
        state[node] = 1
        path.append(node)
        for nxt in sorted(graph.get(node, ())):
            if state.get(nxt) == 1:
                return path[path.index(nxt):] + [nxt]
            if nxt not in state:
                cycle = visit(nxt)
                if cycle:
                    return cycle
        path.pop()
        state[node] = 2
        return None

    for node in sorted(graph):
        if node not in state:
            cycle = visit(node)
            if cycle:
                return cycle
    return None


# -- the checker itself, on small graphs and sources -----------------------------------------------

def test_find_cycle_on_known_graphs():
    assert find_cycle({"a": {"b"}, "b": {"c"}, "c": set()}) is None
    assert find_cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}}) == ["a", "b", "c", "a"]
    assert find_cycle({"a": {"a"}}) == ["a", "a"]


def test_resolve_relative_imports():
    assert resolve("fsof_torch.estimation.flow_fit", 1, "solver") == "fsof_torch.estimation.solver"
    assert resolve("fsof_torch.estimation.flow_fit", 2, "geometry.camera") == "fsof_torch.geometry.camera"
    assert resolve("fsof_torch.estimation", 1, "solver") == "fsof_torch.estimation.solver"  # a package's __init__
    assert resolve("fsof_torch", 1, None) == "fsof_torch"


def test_function_level_imports_are_counted():
    source = ("import math\nfrom .camera import Camera\n\n"
              "def f():\n    if True:\n        from ..estimation import solver\n        from .. import io\n")
    assert dependencies("fsof_torch.geometry.road_models", source) == {
        "fsof_torch.geometry.camera", "fsof_torch.estimation.solver", "fsof_torch.io"}


# -- the rules -------------------------------------------------------------------------------------

def test_no_import_cycles():
    graph = {name: dependencies(name) for name in MODULES}
    cycle = find_cycle(graph)
    assert cycle is None, "import cycle: " + " -> ".join(cycle)


def test_no_private_names_imported_across_modules():
    allowed = {"fsof_torch._check"}
    bad = []
    for name in MODULES:
        for module, names, line in imports(name):
            if not module.startswith("fsof_torch") or module in allowed:
                continue
            private = [n for n in names if n.startswith("_") and not n.startswith("__")
                       and f"{module}.{n}" not in allowed]
            # a private module of the package (``from . import _x``) counts as well
            private += [p for p in module.split(".")[1:] if p.startswith("_") and not p.startswith("__")
                        and module not in allowed]
            if private:
                bad.append(f"{MODULES[name].relative_to(PACKAGE.parent)}:{line} imports {private} from {module}")
    assert bad == []


def test_no_module_over_700_lines():
    long = {str(p.relative_to(PACKAGE.parent)): n for p in MODULES.values()
            if (n := len(p.read_text().splitlines())) > MAX_LINES}
    assert long == {}


# -- the public contract -------------------------------------------------------------------------

def contract_names(text: str) -> list[str]:
    """The names of the design's §9 table: ``fsof_torch.X`` (and ``fsof_torch.metrics.a / b``)."""
    section = text.split("## 9.", 1)[1].split("\n## ", 1)[0]
    names = []
    for cell in re.findall(r"^\| `fsof_torch\.([^`(]+)", section, flags=re.M):
        head, *rest = [part.strip() for part in cell.split("/")]
        names.append(head)
        prefix = head.rsplit(".", 1)[0] + "." if "." in head else ""
        names.extend(prefix + r for r in rest)
    return names


def test_contract_parser_on_a_sample():
    sample = ("## 9. The public contract\n\n| name | does |\n| --- | --- |\n"
              "| `fsof_torch.Camera(K, height)` | x |\n| `fsof_torch.metrics.a / b` | y |\n\n## 10. Next\n"
              "| `fsof_torch.not_here` | z |\n")
    assert contract_names(sample) == ["Camera", "metrics.a", "metrics.b"]


#: the names of DESIGN.md's public contract (section 9), checked without it too (a fresh clone has no
#: ../shared); where DESIGN.md is there, its table must name exactly these
CONTRACT = ("Camera", "displacement_flow", "velocity_flow", "DisplacementFlow", "fit_displacement", "fit_velocity",
            "fit_road", "warp_backward", "photometric_error", "FreespaceRefiner", "FreespaceRefined",
            "FreespaceFlowLoss", "metrics.angular_error", "metrics.endpoint_error", "metrics.u_error",
            "metrics.v_error")


def test_every_contract_name_is_importable_from_fsof_torch():
    names = list(CONTRACT)
    if DESIGN.is_file():
        assert contract_names(DESIGN.read_text()) == names
    missing = []
    for name in names:
        obj = fsof_torch
        for part in name.split("."):
            obj = getattr(obj, part, None)
        if obj is None:
            missing.append(name)
    assert missing == []
    # each top-level name is in __all__ (a star import gets it) and its module imports cleanly
    top = {n.split(".")[0] for n in names}
    assert sorted(top - set(fsof_torch.__all__)) == []
    for name in top:
        obj = getattr(fsof_torch, name)
        importlib.import_module(getattr(obj, "__module__", None) or obj.__name__)


def test_importing_the_library_and_the_jobs_leaves_torch_compile_unloaded():
    """``import fsof_torch`` (and the jobs' modules) must not load torch._dynamo (the compiler: a
    slow import): code that only runs under torch.compile marks itself while compiling (a
    ``@torch.compiler.disable`` decorator at import time would load it for every user)."""
    import subprocess
    import sys

    code = ("import sys, fsof_torch, refine.__main__, eval.__main__; "
            "print(sorted(m for m in sys.modules if m.startswith('torch._dynamo')))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True,
                         cwd=PACKAGE.parent)
    assert out.stdout.strip() == "[]", out.stdout[:500]
