"""No import circle in ``vadgs``: every module imports, and the graph of its imports has no cycle.

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


def _imports(name: str, path: Path, modules: dict[str, Path]) -> set[str]:
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    found: set[str] = set()

    def visit(node: ast.AST) -> None:
        if isinstance(node, ast.Import):
            for a in node.names:
                if a.name.split(".")[0] == "vadgs":
                    found.add(a.name if a.name in modules else a.name.rpartition(".")[0])
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")
                base = base[: len(base) - (node.level - 1)]
                target = ".".join([*base, node.module] if node.module else base)
            else:
                target = node.module or ""
            if target.split(".")[0] == "vadgs":
                for a in node.names:
                    sub = f"{target}.{a.name}"
                    found.add(sub if sub in modules else target)
        for child in ast.iter_child_nodes(node):
            visit(child)

    visit(ast.parse(path.read_text(), str(path)))
    found.discard(name)
    return {m for m in found if m in modules}


def import_graph() -> nx.DiGraph:
    """``vadgs`` module → the ``vadgs`` modules it imports."""
    modules = _modules()
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


# Names a module re-exported before issue 41 (re-exports only in a package's ``__init__``), and the
# module that defines them: the old import still works, with a DeprecationWarning naming the new place.
MOVED = {
    "vadgs.train.vad.reconstruct": {
        "MatchScale": "vadgs.train.vad.crops",
        "ReconstructConfig": "vadgs.train.vad.reconstruct_config",
        "ViewCache": "vadgs.train.vad.visibility",
        "VisibilityIndex": "vadgs.train.vad.visibility",
        "build_visibility_index": "vadgs.train.vad.visibility",
        "derive_instance_map": "vadgs.train.vad.instances",
        "match_scale": "vadgs.train.vad.crops",
        "sfm_observations": "vadgs.train.vad.inputs",
        "thin_points": "vadgs.train.vad.fusion",
    },
}


@pytest.mark.parametrize("old, name", [(m, n) for m, names in MOVED.items() for n in names])
def test_moved_names_import_from_the_old_place_with_a_warning(old, name):
    new = MOVED[old][name]
    module = importlib.import_module(old)
    assert name not in vars(module) and name not in module.__all__  # not bound there any more
    with pytest.warns(DeprecationWarning, match=rf"^{old}\.{name} moved: import it from {new}$") as caught:
        exec(f"from {old} import {name} as got", namespace := {})
    assert namespace["got"] is getattr(importlib.import_module(new), name)
    assert caught[0].filename == "<string>"  # the warning points at the importing line
    with pytest.raises(AttributeError, match=f"has no attribute '{name}x'"):
        getattr(module, f"{name}x")
