"""No import circle in ``vadgs``: every module imports, the graph of its imports has no cycle, and
no module imports from a package above its own (:data:`FLOORS`).

The graph is read from the source (AST): module-level imports, the lazy ones inside functions
(a lazy import only hides a circle until the function runs) and those of ``if TYPE_CHECKING:``
blocks (never executed, but a circle of type hints is still two modules that know each other:
the design has no one-way flow). ``from vadgs.pkg import name`` depends on ``vadgs.pkg.name`` when
that is a module, else on ``vadgs.pkg`` (its ``__init__``).
"""

from __future__ import annotations

import ast
import importlib
import pkgutil
from collections.abc import Iterator
from pathlib import Path

import networkx as nx
import pytest

import vadgs

ROOT = Path(vadgs.__file__).parent


def _modules() -> dict[str, Path]:
    out = {"vadgs": ROOT / "__init__.py"}
    for info in pkgutil.walk_packages([str(ROOT)], prefix="vadgs."):
        rel = Path(*info.name.split(".")[1:])
        path = ROOT / rel / "__init__.py" if info.ispkg else (ROOT / rel).with_suffix(".py")
        out[info.name] = path
    return out


def _from_module(node: ast.ImportFrom, package: str) -> str:
    """The absolute module of ``from ... import`` in ``package`` (relative imports resolved)."""
    if not node.level:
        return node.module or ""
    base = package.split(".")
    base = base[: len(base) - (node.level - 1)]
    return ".".join([*base, node.module] if node.module else base)


def _imports(name: str, path: Path, modules: dict[str, Path]) -> set[str]:
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    found: set[str] = set()

    def visit(node: ast.AST) -> None:
        if isinstance(node, ast.Import):
            for a in node.names:
                if a.name.split(".")[0] == "vadgs":
                    found.add(a.name if a.name in modules else a.name.rpartition(".")[0])
        elif isinstance(node, ast.ImportFrom):
            target = _from_module(node, package)
            if target.split(".")[0] == "vadgs":
                for a in node.names:
                    sub = f"{target}.{a.name}"
                    found.add(sub if sub in modules else target)
        for child in ast.iter_child_nodes(node):
            visit(child)

    visit(ast.parse(path.read_text(), str(path)))
    found.discard(name)
    return {m for m in found if m in modules}


def import_graph(modules: dict[str, Path] | None = None) -> nx.DiGraph:
    """``vadgs`` module → the ``vadgs`` modules it imports (of ``modules``: default, the real ones)."""
    modules = _modules() if modules is None else modules
    g = nx.DiGraph()
    for name, path in modules.items():
        g.add_node(name)
        for dep in _imports(name, path, modules):
            g.add_edge(name, dep)
    return g


@pytest.mark.parametrize("name", sorted(n for n in _modules() if not n.endswith(".__main__")))
def test_every_module_imports(name):
    if name == "vadgs.viewer":
        pytest.importorskip("viser")
    importlib.import_module(name)


def test_python_m_vadgs_cli_is_the_command(capsys, monkeypatch):
    import runpy
    import sys

    monkeypatch.setattr(sys, "argv", ["vadgs", "--help"])
    with pytest.raises(SystemExit) as e:
        runpy.run_module("vadgs.cli", run_name="__main__")
    assert e.value.code == 0 and "train" in capsys.readouterr().out


def test_no_import_circle():
    g = import_graph()
    assert g.number_of_nodes() > 60 and g.number_of_edges() > 150  # the graph was read
    circles = sorted(sorted(c) for c in nx.simple_cycles(g))
    assert circles == [], f"import circles in vadgs: {circles}"
    # the batch trains through the library call, not through the CLI
    assert g.has_edge("vadgs.batch", "vadgs.train.run") and not g.has_edge("vadgs.batch", "vadgs.cli")


def test_the_graph_sees_lazy_and_type_checking_imports(tmp_path, monkeypatch):
    pkg = tmp_path / "vadgs"
    pkg.mkdir()
    (pkg / "__init__.py").write_text("")
    (pkg / "a.py").write_text("def f():\n    from vadgs import b\n")
    (pkg / "b.py").write_text(
        "from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from vadgs.c import C\nfrom . import a\n"
    )
    (pkg / "c.py").write_text("")
    modules = {"vadgs": pkg / "__init__.py", **{f"vadgs.{m}": pkg / f"{m}.py" for m in "abc"}}
    assert _imports("vadgs.a", pkg / "a.py", modules) == {"vadgs.b"}
    assert _imports("vadgs.b", pkg / "b.py", modules) == {"vadgs.a", "vadgs.c"}


# Issue 50: the packages' order. Imports flow one way, down the floors (docs/design.md, ARCHITECTURE):
# tools that import nothing of vadgs; geometry and the run folder's tools; what stands on geometry
# (data feeds the methods, render / mvs / select are them); train, which sees everything; what
# drives train (batch, the viewer); the command line on top. A module imports from its own package
# or from a package on a lower floor, never from one on its floor or above, lazily or under
# ``if TYPE_CHECKING:`` included. A new top-level module or package takes a floor here.
FLOORS: tuple[frozenset[str], ...] = (
    frozenset({"checks", "config", "io", "process"}),
    frozenset({"vadgs", "geometry", "runfolder", "runlock", "viz"}),
    frozenset({"data", "mvs", "render", "select"}),
    frozenset({"train"}),
    frozenset({"batch", "viewer"}),
    frozenset({"cli"}),
)


def _package(module: str) -> str:
    """The top-level package (or module) of ``vadgs`` a module belongs to; ``"vadgs"`` for the root."""
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else parts[0]


def _floor_errors(graph: nx.DiGraph, floors: tuple[frozenset[str], ...]) -> list[str]:
    """Each import that does not go down the floors, and each package without a floor."""
    floor = {p: i for i, ps in enumerate(floors) for p in ps}
    found = [f"{p}: on no floor" for p in sorted({_package(m) for m in graph}) if p not in floor]
    for a, b in sorted(graph.edges()):
        pa, pb = _package(a), _package(b)
        if pa != pb and pa in floor and pb in floor and floor[pb] >= floor[pa]:
            found.append(f"{a} (floor {floor[pa]}) imports {b} (floor {floor[pb]})")
    return found


def test_imports_go_down_the_floors():
    g = import_graph()
    assert {_package(m) for m in g} == set().union(*FLOORS), "a floor names a package that is gone"
    assert _floor_errors(g, FLOORS) == []
    # the packages the design names stand where it says
    floor = {p: i for i, ps in enumerate(FLOORS) for p in ps}
    assert floor["geometry"] < floor["render"] == floor["mvs"] == floor["select"] < floor["train"]
    assert floor["data"] < floor["train"] < floor["cli"]


def test_the_scan_sees_an_upward_import(tmp_path):
    pkg = tmp_path / "vadgs"
    for sub in ("geometry", "data", "train"):
        (pkg / sub).mkdir(parents=True)
        (pkg / sub / "__init__.py").write_text("")
    (pkg / "__init__.py").write_text("")
    (pkg / "geometry" / "a.py").write_text("def f():\n    from vadgs.train import t\n")  # lazy, upward
    (pkg / "data" / "d.py").write_text(
        "from typing import TYPE_CHECKING\nfrom vadgs.geometry import a\n"  # down: allowed
        "if TYPE_CHECKING:\n    from vadgs.train.t import T\n"  # a type hint, upward
    )
    (pkg / "train" / "t.py").write_text("from vadgs.data import d\nfrom ..geometry.a import f\n")  # down
    (pkg / "tools.py").write_text("")
    modules = {
        "vadgs": pkg / "__init__.py",
        "vadgs.tools": pkg / "tools.py",
        **{f"vadgs.{s}": pkg / s / "__init__.py" for s in ("geometry", "data", "train")},
        "vadgs.geometry.a": pkg / "geometry" / "a.py",
        "vadgs.data.d": pkg / "data" / "d.py",
        "vadgs.train.t": pkg / "train" / "t.py",
    }
    floors = (frozenset({"vadgs", "geometry"}), frozenset({"data"}), frozenset({"train"}))
    assert _floor_errors(import_graph(modules), floors) == [
        "tools: on no floor",
        "vadgs.data.d (floor 1) imports vadgs.train.t (floor 2)",
        "vadgs.geometry.a (floor 0) imports vadgs.train.t (floor 2)",
    ]
    # a sideways import (one floor, two packages) is refused as well
    sideways = (frozenset({"vadgs", "geometry", "tools"}), frozenset({"data", "train"}))
    assert _floor_errors(import_graph(modules), sideways) == [
        "vadgs.data.d (floor 1) imports vadgs.train.t (floor 1)",
        "vadgs.geometry.a (floor 0) imports vadgs.train.t (floor 1)",
        "vadgs.train.t (floor 1) imports vadgs.data.d (floor 1)",
    ]


# Issue 41: a module imports only public names of another (what one module needs of another is
# part of the other's API: public, documented, in its ``__all__``), and re-exports happen only in a
# package's ``__init__`` (a module's ``__all__`` lists only what it defines).

# (importing module, module imported from, name): private names allowed to be imported across
# modules. None.
PRIVATE_IMPORTS_ALLOWED: set[tuple[str, str, str]] = set()


def _private_imports(modules: dict[str, Path]) -> set[tuple[str, str, str]]:
    """``(module, imported from, name)`` of every private name a vadgs module imports from another.

    Every ``from ... import`` counts (module level, in functions, under ``if TYPE_CHECKING:``);
    a private *module* (``from vadgs.data import _tracks``) is not a name, nor are dunders.
    """
    found = set()
    for name, path in modules.items():
        package = name if path.name == "__init__.py" else name.rpartition(".")[0]
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if not isinstance(node, ast.ImportFrom):
                continue
            target = _from_module(node, package)
            if target.split(".")[0] != "vadgs" or target == name:
                continue
            for a in node.names:
                private = a.name.startswith("_") and not a.name.endswith("__")
                if private and f"{target}.{a.name}" not in modules:
                    found.add((name, target, a.name))
    return found


def test_no_private_name_is_imported_from_another_module():
    found = _private_imports(_modules())
    assert found - PRIVATE_IMPORTS_ALLOWED == set(), "private names imported across vadgs modules"
    assert PRIVATE_IMPORTS_ALLOWED <= found, "allowed but gone: shrink PRIVATE_IMPORTS_ALLOWED"


def _from_imports(files: list[Path], root: Path) -> Iterator[tuple[Path, ast.ImportFrom, str, list[str]]]:
    """``(file relative to root, node, module imported from, names)`` of every ``from ... import`` in
    ``files``, at any depth (module level, in functions, under ``if TYPE_CHECKING:``)."""
    for path in files:
        rel = path.relative_to(root)
        name = ".".join(rel.with_suffix("").parts)
        package = name.removesuffix(".__init__") if path.name == "__init__.py" else name.rpartition(".")[0]
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.ImportFrom):
                yield rel, node, _from_module(node, package), [a.name for a in node.names]


def _private_imports_in(files: list[Path], root: Path, modules: dict[str, Path]) -> set[tuple[str, str, str]]:
    """``(file, imported from, name)`` of every private name ``files`` import from ``vadgs`` or ``tests``.

    The tests use what they test through its public name, as any caller (issue 50, item 6): a helper
    shared by several test modules is public in its own. A private *module* is not a name, nor are
    dunders; foreign libraries are not scanned (gsplat's pure-torch references, which the tests compare
    against, are reachable only under private names).
    """
    found = set()
    for rel, _node, target, names in _from_imports(files, root):
        if target.split(".")[0] not in ("vadgs", "tests"):
            continue
        for a in names:
            private = a.startswith("_") and not a.endswith("__")
            sub = f"{target}.{a}"
            a_module = sub in modules or (root / Path(*sub.split("."))).with_suffix(".py").exists()
            if private and not a_module:
                found.add((str(rel), target, a))
    return found


def test_no_private_name_is_imported_by_the_tests():
    files = sorted((REPO / "tests").rglob("*.py"))
    assert len(files) > 100  # the tests were read
    assert _private_imports_in(files, REPO, _modules()) == set()


def test_the_scan_of_the_tests_sees_private_imports(tmp_path):
    (tmp_path / "tests" / "sub").mkdir(parents=True)
    (tmp_path / "tests" / "__init__.py").write_text("")
    (tmp_path / "tests" / "sub" / "__init__.py").write_text("")
    (tmp_path / "tests" / "sub" / "_impl.py").write_text("")
    (tmp_path / "tests" / "sub" / "helpers.py").write_text("def _h(): pass\ndef h(): pass\n")
    (tmp_path / "tests" / "sub" / "test_a.py").write_text(
        "from vadgs.train.vad.reconstruct import select_supports, _select_among\n"
        "from vadgs.cli import main as _main\n"  # a public name under a private alias: allowed
        "from tests.sub import _impl\n"  # a private module: allowed
        "from gsplat.cuda._torch_impl import _quat_scale_to_covar_preci\n"  # foreign: not scanned
        "def test_x():\n    from .helpers import _h, h\n"
    )
    files = sorted((tmp_path / "tests").rglob("*.py"))
    assert _private_imports_in(files, tmp_path, _modules()) == {
        ("tests/sub/test_a.py", "vadgs.train.vad.reconstruct", "_select_among"),
        ("tests/sub/test_a.py", "tests.sub.helpers", "_h"),
    }


def _defined_and_all(tree: ast.Module) -> tuple[set[str], list[str] | None]:
    """The names a module's own top-level code binds (not its imports), and its ``__all__``."""
    defined: set[str] = set()
    listed = None

    def visit(stmts: list[ast.stmt]) -> None:
        nonlocal listed
        for s in stmts:
            if isinstance(s, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
                defined.add(s.name)
            elif isinstance(s, (ast.Assign, ast.AnnAssign, ast.AugAssign)):
                targets = s.targets if isinstance(s, ast.Assign) else [s.target]
                for tgt in targets:
                    defined.update(n.id for n in ast.walk(tgt) if isinstance(n, ast.Name))
                if any(isinstance(tgt, ast.Name) and tgt.id == "__all__" for tgt in targets):
                    listed = [*(listed if isinstance(s, ast.AugAssign) else []), *ast.literal_eval(s.value)]
            elif isinstance(s, (ast.If, ast.Try, ast.With, ast.For)):  # top-level blocks, not bodies
                for block in ("body", "orelse", "finalbody"):
                    visit(getattr(s, block, []))
                for h in getattr(s, "handlers", []):
                    visit(h.body)

    visit(tree.body)
    return defined, listed


def _reexports(modules: dict[str, Path]) -> dict[str, list[str]]:
    """Module → the names its ``__all__`` lists but it does not define (packages' ``__init__`` aside)."""
    out = {}
    for name, path in modules.items():
        if path.name == "__init__.py":
            continue
        defined, listed = _defined_and_all(ast.parse(path.read_text(), str(path)))
        foreign = [n for n in listed or [] if n not in defined]
        if foreign:
            out[name] = foreign
    return out


def test_only_packages_reexport():
    assert _reexports(_modules()) == {}, "a module's __all__ lists names it imports (re-export from __init__)"


def test_the_scans_see_private_imports_and_reexports(tmp_path):
    pkg = tmp_path / "vadgs"
    (pkg / "sub").mkdir(parents=True)
    (pkg / "__init__.py").write_text("from vadgs.a import f\n__all__ = ['f']\n")
    (pkg / "a.py").write_text("def f(): pass\ndef _g(): pass\n__all__ = ['f']\n")
    (pkg / "sub" / "__init__.py").write_text("")
    (pkg / "sub" / "_impl.py").write_text("")
    (pkg / "sub" / "b.py").write_text(
        "from typing import TYPE_CHECKING\n"
        "from vadgs.sub import _impl\n"  # a private module: allowed
        "from vadgs import __doc__ as d\n"  # a dunder: allowed
        "if TYPE_CHECKING:\n    from ..a import _g\n"
        "def h():\n    from vadgs.a import _g, f\n"
        "X, (Y, Z) = 1, (2, 3)\n"
        "try:\n    import json as W\nexcept ImportError:\n    W = None\n"
        "__all__ = ['X', 'Z', 'f', 'h']\n__all__ += ['W']\n"
    )
    modules = {
        "vadgs": pkg / "__init__.py",
        "vadgs.a": pkg / "a.py",
        "vadgs.sub": pkg / "sub" / "__init__.py",
        "vadgs.sub._impl": pkg / "sub" / "_impl.py",
        "vadgs.sub.b": pkg / "sub" / "b.py",
    }
    assert _private_imports(modules) == {("vadgs.sub.b", "vadgs.a", "_g")}
    assert _reexports(modules) == {"vadgs.sub.b": ["f"]}  # W is bound by the module (its fallback)


# Issue 50: a name lives in one place and is imported from there: from the module that defines it, or
# from its package's ``__init__`` (the public face), never through another module that happens to
# import it, nor through a package it does not belong to. Nothing is kept for compatibility.

REPO = ROOT.parent


def _defines(modules: dict[str, Path]) -> dict[str, tuple[set[str], set[str]]]:
    """Module → (the names its own code binds, the names it lists in ``__all__`` as a package)."""
    out = {}
    for name, path in modules.items():
        defined, listed = _defined_and_all(ast.parse(path.read_text(), str(path)))
        out[name] = (defined, set(listed or []) if path.name == "__init__.py" else set())
    return out


def _misplaced_imports(files: list[Path], modules: dict[str, Path], root: Path) -> list[str]:
    """``file:line module.name`` of every ``from vadgs.module import name`` where ``name`` is neither
    defined in ``module``, a submodule of it, nor listed by it as a package."""
    defines = _defines(modules)
    found = []
    for rel, node, target, names in _from_imports(files, root):
        if target.split(".")[0] != "vadgs" or target not in defines:
            continue
        defined, listed = defines[target]
        for a in names:
            if f"{target}.{a}" not in modules and a not in defined | listed:
                found.append(f"{rel}:{node.lineno} {target}.{a}")
    return found


def _package_foreign_names(modules: dict[str, Path]) -> list[str]:
    """``package.name`` of every name a package's ``__all__`` lists from outside the package."""
    found = []
    for name, path in modules.items():
        if path.name != "__init__.py":
            continue
        tree = ast.parse(path.read_text(), str(path))
        source = {}
        for node in ast.walk(tree):
            if isinstance(node, ast.ImportFrom):
                target = _from_module(node, name)
                source.update({a.asname or a.name: target for a in node.names})
        _, listed = _defined_and_all(tree)
        for n in listed or []:
            target = source.get(n, name)
            if target != name and not target.startswith(name + "."):
                found.append(f"{name}.{n} (from {target})")
    return found


def test_names_are_imported_from_where_they_live():
    files = [
        p for d in ("vadgs", "tests", "benchmarks", "examples", "tools") for p in (REPO / d).rglob("*.py")
    ]
    assert len(files) > 200  # the repository was read
    assert _misplaced_imports(files, _modules(), REPO) == []
    assert _package_foreign_names(_modules()) == []
    assert not (ROOT / "deprecation.py").exists()


def test_the_scan_sees_a_name_imported_through_another_module(tmp_path):
    pkg = tmp_path / "vadgs"
    (pkg / "sub").mkdir(parents=True)
    (pkg / "__init__.py").write_text("")
    (pkg / "a.py").write_text("def f(): pass\n")
    (pkg / "sub" / "__init__.py").write_text(
        "from vadgs.a import f\nfrom vadgs.sub.b import g\n__all__ = ['f', 'g']\n"
    )
    (pkg / "sub" / "b.py").write_text("from vadgs.a import f\ndef g(): pass\n")
    (tmp_path / "t.py").write_text(
        "from vadgs.sub.b import f, g\nfrom vadgs.sub import g\nfrom vadgs import a\n"
    )
    modules = {
        "vadgs": pkg / "__init__.py",
        "vadgs.a": pkg / "a.py",
        "vadgs.sub": pkg / "sub" / "__init__.py",
        "vadgs.sub.b": pkg / "sub" / "b.py",
    }
    assert _misplaced_imports([tmp_path / "t.py"], modules, tmp_path) == ["t.py:1 vadgs.sub.b.f"]
    assert _package_foreign_names(modules) == ["vadgs.sub.f (from vadgs.a)"]
