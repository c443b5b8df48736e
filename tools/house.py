"""The structure of the package, as a newcomer would draw it from the imports.

    python tools/house.py [REPO] [-v] [-c]

Rooms are the subpackages (``fusion``, ``io``, ...) and the top-level modules; an arrow is an import
between two modules (module arrows) or two rooms (room arrows); floors are the longest chain of room
arrows once cycles are merged, and the longest walk is that chain. Also counted: imports inside
functions (``-v`` lists them; Mitsuba, viser, pycolmap, matplotlib and torch are optional
dependencies), ``section(`` calls outside the configuration's parsers, room cycles (``-c`` lists their
arrows), imports of the application layer (``cfgs_jax.app``) from below it and functions over 60
lines outside ``splat/``.
"""

from __future__ import annotations

import ast
import collections
import pathlib
import sys

OPTIONAL = ("mitsuba", "drjit", "viser", "pycolmap", "matplotlib", "torch", "lpips", "OpenEXR", "Imath")
PARSERS = ("cfgs_jax.config", "cfgs_jax.fusion.config", "cfgs_jax.evaluation.protocol")


def modules(root: pathlib.Path) -> dict[str, pathlib.Path]:
    out = {}
    for p in root.rglob("*.py"):
        name = ".".join(p.relative_to(root.parent).with_suffix("").parts)
        out[name.removesuffix(".__init__")] = p
    return out


def room(module: str) -> str:
    parts = module.split(".")
    return ".".join(parts[:2])


def imported(node, package: str, mods) -> list[str]:
    """The modules an import statement names (a package's submodules, else the package itself)."""
    if isinstance(node, ast.Import):
        return [a.name for a in node.names]
    if node.level:
        base = package.split(".")
        base = base[: len(base) - (node.level - 1)]
        mod = ".".join(base + ([node.module] if node.module else []))
    else:
        mod = node.module or ""
    out = [f"{mod}.{a.name}" for a in node.names if f"{mod}.{a.name}" in mods]
    return out if len(out) == len(node.names) else [mod, *out]


def survey(root: pathlib.Path):
    mods = modules(root)
    edges, inner, long, sections = set(), [], [], collections.Counter()
    for name, p in mods.items():
        tree = ast.parse(p.read_text())
        package = name if p.name == "__init__.py" else name.rsplit(".", 1)[0]
        for node in ast.walk(tree):
            if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
                lines = node.end_lineno - node.lineno + 1
                if lines > 60 and "/splat/" not in str(p):
                    long.append((lines, f"{name}.{node.name}"))
                for sub in ast.walk(node):
                    if isinstance(sub, ast.Import | ast.ImportFrom):
                        inner.append((name, node.name, imported(sub, package, mods)[0]))
            if isinstance(node, ast.Call):
                called = getattr(node.func, "id", getattr(node.func, "attr", None))
                if called == "section":
                    sections[name] += 1
            if isinstance(node, ast.Import | ast.ImportFrom):
                for target in imported(node, package, mods):
                    if target in mods and target != name:
                        edges.add((name, target))
    return mods, edges, inner, long, sections


def strongly_connected(nodes, graph) -> list[list[str]]:
    index, low, stack, on, out, counter = {}, {}, [], set(), [], [0]

    def visit(v):
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on.add(v)
        for w in graph[v]:
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
            out.append(comp)

    for v in nodes:
        if v not in index:
            visit(v)
    return out


def room_graph(mods, edges) -> tuple[list[str], set, list[list[str]]]:
    """The rooms, the arrows between them, and their strongly connected components (a cycle: one of
    more than one room)."""
    rooms = sorted({room(m) for m in mods})
    room_edges = {(room(a), room(b)) for a, b in edges if room(a) != room(b)}
    graph = collections.defaultdict(set)
    for a, b in room_edges:
        graph[a].add(b)
    return rooms, room_edges, strongly_connected(rooms, graph)


def room_cycles(repo: pathlib.Path) -> list[list[str]]:
    """The room cycles of the package under ``repo``: sets of rooms whose imports lead round in a circle."""
    sys.setrecursionlimit(max(sys.getrecursionlimit(), 10000))
    mods, edges, *_ = survey(pathlib.Path(repo) / "src" / "cfgs_jax")
    return [s for s in room_graph(mods, edges)[2] if len(s) > 1]


def upward_arrows(repo: pathlib.Path) -> list[tuple[str, str]]:
    """Imports of the application layer (``cfgs_jax.app``) from below it: every module but the entry
    point ``cfgs_jax.pipeline`` must work without the command line, the viewer or the web page."""
    mods, edges, *_ = survey(pathlib.Path(repo) / "src" / "cfgs_jax")
    top = ("cfgs_jax.app", "cfgs_jax.pipeline")
    return sorted((a, b) for a, b in edges if room(b) == "cfgs_jax.app" and room(a) not in top)


def long_functions(repo: pathlib.Path) -> list[tuple[int, str]]:
    """The functions of the package under ``repo`` over 60 lines outside ``splat/`` (lines, name)."""
    return sorted(survey(pathlib.Path(repo) / "src" / "cfgs_jax")[3], reverse=True)


def main() -> None:
    args = [a for a in sys.argv[1:] if not a.startswith("-")]
    root = pathlib.Path(args[0] if args else ".") / "src" / "cfgs_jax"
    sys.setrecursionlimit(10000)
    mods, edges, inner, long, sections = survey(root)
    rooms, room_edges, sccs = room_graph(mods, edges)
    comp = {v: i for i, s in enumerate(sccs) for v in s}
    condensed = collections.defaultdict(set)
    for a, b in room_edges:
        if comp[a] != comp[b]:
            condensed[comp[a]].add(comp[b])

    walks: dict[int, list[str]] = {}

    def walk(c: int) -> list[str]:
        if c not in walks:
            best = max((walk(d) for d in condensed[c]), key=len, default=[])
            walks[c] = [sccs[c][0], *best]
        return walks[c]

    longest = max((walk(i) for i in range(len(sccs))), key=len)
    cycles = [s for s in sccs if len(s) > 1]
    required = [i for i in inner if i[2].split(".")[0] not in OPTIONAL]
    outside = {k: v for k, v in sections.items() if k not in PARSERS}
    print(f"rooms {len(rooms)}, module arrows {len(edges)}, room arrows {len(room_edges)}, floors {len(longest)}")
    print(f"imports inside functions {len(inner)}, of which not of an optional dependency {len(required)}")
    print(f"section( calls outside the parsers {sum(outside.values())} {outside}")
    print(f"room cycles {cycles}")
    print(f"imports of the application layer from below it: {upward_arrows(root.parent.parent)}")
    print("longest walk: " + " → ".join(longest))
    print(f"functions over 60 lines outside splat/: {sorted(long, reverse=True)}")
    if "-v" in sys.argv:
        for i in required:
            print("  inside a function:", i)
    if "-c" in sys.argv:
        members = {v for s in cycles for v in s}
        for a, b in sorted(edges):
            if room(a) in members and room(b) in members and room(a) != room(b):
                print("  arrow in a cycle:", a, "→", b)


if __name__ == "__main__":
    main()
