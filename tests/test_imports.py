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
    "vadgs.data.colmap": {"match_colmap_views": "vadgs.data.colmap_model"},
    "vadgs.data.dgp": {"points_in_boxes": "vadgs.data._tracks"},
    "vadgs.train.vad.incomplete": {"voxel_labels": "vadgs.geometry.voxel"},
    "vadgs.train.run": {
        "BenchmarkRef": "vadgs.train.scenes",
        "DGPRef": "vadgs.train.scenes",
        "RunInUseError": "vadgs.train.session",
        "SceneRef": "vadgs.train.scenes",
        "clear_run": "vadgs.train.checkpoint",
        "locate_scene": "vadgs.train.scenes",
        "open_scene": "vadgs.train.scenes",
        "scene_fingerprint": "vadgs.train.scenes",
        "scene_ref": "vadgs.train.scenes",
    },
    "vadgs.train.trainer": {
        "DivergenceError": "vadgs.train.divergence",
        "GeometryTargets": "vadgs.train.losses",
        "LearningRates": "vadgs.train.config",
        "RESUMABLE_CHANGES": "vadgs.train.checkpoint",
        "TrainResult": "vadgs.train.loop",
        "checkpoint_checksum": "vadgs.train.checkpoint",
        "clear_run": "vadgs.train.checkpoint",
        "lidar_depth_map": "vadgs.data.lidar",
    },
}
# Names a module re-exported before and still imports because it uses them: no longer in its
# ``__all__`` (nor imported from there in the repository), but the old import keeps working.
KEPT = {
    "vadgs.data.colmap": {
        "COLMAP_PIXEL_OFFSET": "vadgs.data.colmap_model",
        "ColmapPoints": "vadgs.data.scene",
        "colmap_camera_to_K": "vadgs.data.colmap_model",
        "distorted_cameras": "vadgs.data.colmap_model",
        "find_colmap_model": "vadgs.data.colmap_model",
    },
    "vadgs.data.waymo": {
        "waymo_beam_inclinations": "vadgs.data.waymo_lidar",
        "waymo_range_image_to_points": "vadgs.data.waymo_lidar",
    },
    "vadgs.render.splat": {"RasterConfig": "vadgs.render.common", "RenderOutput": "vadgs.render.common"},
    "vadgs.train.run": {
        "ColmapRef": "vadgs.train.scenes",
        "RunLock": "vadgs.train.session",
        "describe_run": "vadgs.train.checkpoint",
        "open_run_scene": "vadgs.train.scenes",
        "prepare_scene": "vadgs.train.scenes",
    },
    "vadgs.train.trainer": {
        "CHECKPOINT_NAME": "vadgs.train.checkpoint",
        "NonFiniteLossError": "vadgs.train.divergence",
        "TrainConfig": "vadgs.train.config",
        "describe_run": "vadgs.train.checkpoint",
        "load_checkpoint": "vadgs.train.checkpoint",
        "open_scene": "vadgs.train.scenes",
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


@pytest.mark.parametrize("old, name", [(m, n) for m, names in KEPT.items() for n in names])
def test_kept_names_still_import_from_the_old_place(old, name):
    module = importlib.import_module(old)
    assert name not in module.__all__
    assert getattr(module, name) is getattr(importlib.import_module(KEPT[old][name]), name)
