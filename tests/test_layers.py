"""The house's import graph, read with ``ast``: one-way layers and no circles.

Every ``import`` and ``from ... import`` of ``firmware/``, ``sim/`` and ``host/`` counts,
also the ones inside functions (a lazy import is still a dependency: that is how the old
``host/hil.py`` <-> ``host/faults.py`` circle hid).  Modules named only in strings (the CLI's
lazy command table, the bench table) are not edges.

The layer order, lowest first, is :data:`LAYERS`; a module may import its own layer and
the layers below it.  README.md's "Layout" section shows the same order.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
PACKAGES = ("firmware", "sim", "host")

# lowest first: data flows parameters -> model -> design -> tables -> firmware -> link -> plant
LAYERS: tuple[str, ...] = (
    "firmware",
    "sim",
    "host.design",
    "host.link",
    "host.boards",
    "host.hil",
    "host.studies",
    "host.operate",
    "host.dashboard",
    "host.bench",
    "host.cli",
)


def module_name(path: Path, root: Path) -> str:
    """Dotted module name of a file under ``root`` (``pkg/__init__.py`` -> ``pkg``)."""
    parts = list(path.relative_to(root).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def imports_of(path: Path, root: Path) -> set[str]:
    """Project modules a file imports (absolute names, relative imports resolved)."""
    me = module_name(path, root)
    pkg = me if path.name == "__init__.py" else me.rpartition(".")[0]
    found: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
        if isinstance(node, ast.Import):
            found.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                up = pkg.split(".")
                up = up[: len(up) - (node.level - 1)]
                base = ".".join([*up, base] if base else up)
            found.add(base)
            # `from pkg import module` names a module
            found.update(f"{base}.{a.name}" for a in node.names)
    return {m for m in found if m.split(".")[0] in PACKAGES}


def graph(root: Path = ROOT) -> dict[str, set[str]]:
    """Module -> the project modules it imports (only names that are modules of the tree)."""
    files = [p for pkg in PACKAGES for p in (root / pkg).rglob("*.py") if (root / pkg).is_dir()]
    mods = {module_name(p, root): p for p in files}
    g: dict[str, set[str]] = {}
    for name, path in mods.items():
        deps = set()
        for m in imports_of(path, root):
            # resolve to the longest prefix that is a module of the tree
            while m and m not in mods:
                m = m.rpartition(".")[0]
            if m and m != name and not name.startswith(m + ".") and m not in PACKAGES + ("host",):
                deps.add(m)
        g[name] = deps
    return g


def layer_of(mod: str) -> int | None:
    """Index of the layer a module belongs to (the longest matching prefix), or None."""
    best = None
    for i, prefix in enumerate(LAYERS):
        if mod == prefix or mod.startswith(prefix + "."):
            if best is None or len(prefix) > len(LAYERS[best]):
                best = i
    return best


def violations(g: dict[str, set[str]]) -> list[str]:
    """Imports that run up the layer order, and modules in no layer."""
    out = []
    for mod, deps in sorted(g.items()):
        lm = layer_of(mod)
        if lm is None:
            if mod not in PACKAGES + ("host",):
                out.append(f"{mod}: in no layer of LAYERS")
            continue
        for d in sorted(deps):
            ld = layer_of(d)
            if ld is not None and ld > lm:
                out.append(f"{mod} ({LAYERS[lm]}) imports {d} ({LAYERS[ld]}): against the layer order")
    return out


def circles(g: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components with more than one module (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on: set[str] = set()
    out: list[list[str]] = []
    counter = [0]

    def visit(v: str) -> None:
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on.add(v)
        for w in g.get(v, ()):
            if w not in g:
                continue
            if w not in index:
                visit(w)
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
                out.append(sorted(comp))

    for v in sorted(g):
        if v not in index:
            visit(v)
    return out


def test_no_import_against_the_layer_order():
    bad = violations(graph())
    assert not bad, "\n".join(bad)


def test_no_import_circles():
    found = circles(graph())
    assert not found, "import circles: " + "; ".join(" <-> ".join(c) for c in found)


def test_sim_and_firmware_stay_below_host():
    g = graph()
    for mod, deps in g.items():
        if mod.startswith(("sim", "firmware")):
            assert not {d for d in deps if d.startswith("host")}, mod
        if mod.startswith("firmware"):
            assert not {d for d in deps if d.startswith("sim")}, mod


def _tree(tmp_path: Path, files: dict[str, str]) -> Path:
    for rel, text in files.items():
        p = tmp_path / rel
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_text(text)
    for pkg in PACKAGES:
        (tmp_path / pkg).mkdir(exist_ok=True)
        (tmp_path / pkg / "__init__.py").touch()
    return tmp_path


@pytest.mark.parametrize("files, expect", [
    # a lower layer importing a higher one, inside a function
    ({"sim/plant.py": "def f():\n    from host.design import discrete\n",
      "host/design/__init__.py": "", "host/design/discrete.py": "x = 1\n"}, "against the layer order"),
    # the link importing the HIL session
    ({"host/link/__init__.py": "", "host/link/clients.py": "from host.hil.session import X\n",
      "host/hil/__init__.py": "", "host/hil/session.py": "X = 1\n"}, "against the layer order"),
    # a module outside every layer
    ({"host/misc.py": "x = 1\n"}, "in no layer"),
])
def test_a_wrong_import_is_caught(tmp_path, files, expect):
    bad = violations(graph(_tree(tmp_path, files)))
    assert any(expect in b for b in bad), bad


def test_a_circle_is_caught(tmp_path):
    root = _tree(tmp_path, {
        "host/hil/__init__.py": "",
        "host/hil/session.py": "from host.hil import faults\n",
        "host/hil/faults.py": "def f():\n    from .session import run\n",
    })
    assert circles(graph(root)) == [["host.hil.faults", "host.hil.session"]]


def test_relative_imports_resolve(tmp_path):
    root = _tree(tmp_path, {"sim/a.py": "from .b import x\nfrom . import c\n", "sim/b.py": "x = 1\n", "sim/c.py": ""})
    assert graph(root)["sim.a"] == {"sim.b", "sim.c"}
