"""The package's rooms import only downwards, and no module imports itself back through others.

Rooms, lowest first (``bf_epic_blocks/__init__.py`` draws them):
conventions, cuda (the ground floor) < imaging < station, sky, io, runtime, search < blocks, service < pipeline.
Rooms of the same level may import each other (``io`` uses ``runtime``'s ci4 codec, ``sky`` the
ci4 packer); any cycle between modules fails, lazy (function-level) imports included, because a
cycle hidden in a function is still two modules that cannot be understood apart.

The imports are read with ``ast`` from the source files; nothing is executed.
"""
import ast
from pathlib import Path

import pytest

PKG = "bf_epic_blocks"
ROOT = Path(__file__).resolve().parent.parent / PKG
LEVEL = {"conventions": 0, "cuda": 0, "imaging": 1, "station": 2, "sky": 2, "io": 2, "runtime": 2, "search": 2,
         "blocks": 3, "service": 3, "pipeline": 4}


def _modules():
    """{dotted module name: path} for every .py file of the package."""
    mods = {}
    for path in ROOT.rglob("*.py"):
        parts = list(path.relative_to(ROOT.parent).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts = parts[:-1]
        mods[".".join(parts)] = path
    return mods


MODULES = _modules()


def _is_package(mod):
    return MODULES[mod].name == "__init__.py"


def _imports(mod):
    """(imported module, line) pairs of ``mod``, relative imports resolved, at any depth of the file."""
    tree = ast.parse(MODULES[mod].read_text(), filename=str(MODULES[mod]))
    here = mod.split(".") if _is_package(mod) else mod.split(".")[:-1]
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out += [(a.name, node.lineno) for a in node.names if a.name.split(".")[0] == PKG]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = here[:len(here) - (node.level - 1)]
                target = ".".join(base + ([node.module] if node.module else []))
            else:
                target = node.module or ""
            if target.split(".")[0] != PKG:
                continue
            for a in node.names:   # `from pkg import submodule` imports the submodule
                sub = f"{target}.{a.name}"
                out.append((sub if sub in MODULES else target, node.lineno))
    return out


def _room(mod):
    parts = mod.split(".")
    return parts[1] if len(parts) > 1 else None   # None: the package's own __init__


def _graph():
    return {m: sorted({t for t, _ in _imports(m) if t in MODULES and t != m}) for m in MODULES}


def test_every_room_is_known():
    rooms = {_room(m) for m in MODULES} - {None}
    assert rooms <= set(LEVEL), f"rooms without a level in this test: {sorted(rooms - set(LEVEL))}"


def test_rooms_import_only_downwards():
    bad = []
    for mod in MODULES:
        src = _room(mod)
        if src is None:
            continue                     # the top-level __init__ may re-export from any room
        for target, line in _imports(mod):
            dst = _room(target)
            if dst is not None and dst in LEVEL and LEVEL[dst] > LEVEL[src]:
                bad.append(f"{MODULES[mod].relative_to(ROOT.parent)}:{line} ({src}) imports {target} ({dst})")
    assert not bad, "a lower room imports a higher one:\n" + "\n".join(bad)


def test_nothing_below_pipeline_imports_it():
    offenders = [m for m in MODULES if _room(m) not in (None, "pipeline")
                 and any(_room(t) == "pipeline" for t, _ in _imports(m))]
    assert not offenders, offenders


def _find_cycle(graph):
    """One cycle as a list of modules, or None (iterative DFS, colours)."""
    colour = dict.fromkeys(graph, 0)
    for start in graph:
        if colour[start]:
            continue
        stack = [(start, iter(graph[start]))]
        path = [start]
        colour[start] = 1
        while stack:
            node, it = stack[-1]
            nxt = next(it, None)
            if nxt is None:
                colour[node] = 2
                stack.pop()
                path.pop()
            elif colour[nxt] == 1:
                return path[path.index(nxt):] + [nxt]
            elif colour[nxt] == 0:
                colour[nxt] = 1
                stack.append((nxt, iter(graph[nxt])))
                path.append(nxt)
    return None


def _package_edges_removed(graph):
    """Drop edges from a package's ``__init__`` to its own submodules: re-exports, not cycles."""
    return {m: [t for t in ts if not (_is_package(m) and t.startswith(m + "."))] for m, ts in graph.items()}


def test_no_import_cycles():
    cycle = _find_cycle(_package_edges_removed(_graph()))
    assert cycle is None, "import cycle: " + " -> ".join(cycle)


@pytest.mark.parametrize("graph, expect", [
    ({"a": ["b"], "b": ["c"], "c": ["a"]}, True),
    ({"a": ["b"], "b": ["c"], "c": []}, False),
])
def test_cycle_finder_can_fail(graph, expect):
    assert (_find_cycle(graph) is not None) is expect


def test_layering_check_sees_a_planted_upward_import(tmp_path, monkeypatch):
    """The import reader resolves relative imports, lazy ones included, to the room they reach."""
    planted = tmp_path / "planted.py"
    planted.write_text("def f():\n    from ..pipeline import config\n")
    monkeypatch.setitem(MODULES, f"{PKG}.imaging.planted", planted)
    assert (f"{PKG}.pipeline.config", 2) in _imports(f"{PKG}.imaging.planted")


def test_public_imports():
    import bf_epic_blocks
    from bf_epic_blocks import CalFoldBlock, DFTImagerBlock, WStackBlock, imaging
    from bf_epic_blocks import blocks
    assert DFTImagerBlock is blocks.DFTImagerBlock and WStackBlock is blocks.WStackBlock
    assert CalFoldBlock is blocks.CalFoldBlock and callable(imaging.dirty_image)
    with pytest.raises(AttributeError, match="no attribute"):
        bf_epic_blocks.NoSuchBlock
