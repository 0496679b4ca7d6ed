"""The house's floors (README "Map"): every import points down or sideways, never up, never round.

    6  cli                     the command line (starts the daemon, the web, the demo)
    5  web                     REST API and operator page
    4  station                 the daemon, decisions, records, replay
    3  station.diagnostics     the engineer's model loop
    2  station.science         calibration science
    1  drivers | db            hardware links and simulators | storage (neither imports the other)
    0  contracts               identity, sample blocks, events, log format, recordings

The daemon knows nothing of the web: the web reads the station, the command line starts both, so no
module under station/ imports web (its own test below names any that does).

Within station, science and diagnostics are pure: they import only the ground floor and each other
(science below diagnostics), so a live stream, a replay and a CSV give the same answer.

The check reads every module's imports with `ast` (imports inside functions count too: a lazy
import is still an arrow), so it needs nothing installed and fails on the first upward arrow or
circle, naming the modules.
"""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
PACKAGES = ("contracts", "drivers", "db", "station", "web", "cli")

# (module prefix, rank): the longest matching prefix gives a module its floor.
FLOORS: tuple[tuple[str, int], ...] = (
    ("contracts", 0),
    ("drivers", 1),
    ("db", 1),
    ("station.science", 2),
    ("station.diagnostics", 3),
    ("station", 4),
    ("web", 5),
    ("cli", 6),
)
# Same floor, different houses: these may not import each other either.
SIBLINGS = {frozenset({"drivers", "db"})}


def floor_of(module: str) -> tuple[str, int]:
    best = ("", -1)
    for prefix, rank in FLOORS:
        if (module == prefix or module.startswith(prefix + ".")) and len(prefix) > len(best[0]):
            best = (prefix, rank)
    return best


def module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def imports_of(path: Path, module: str, known: set[str]) -> set[str]:
    """The project modules `path` imports (resolved to the deepest known module)."""
    is_pkg = path.name == "__init__.py"
    out: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        names: list[str] = []
        if isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = module.split(".")
                base = base if is_pkg else base[:-1]
                base = base[: len(base) - (node.level - 1)]
                mod = ".".join(base + ([node.module] if node.module else []))
            else:
                mod = node.module or ""
            # `from pkg import sub` imports the submodule, not (only) the package
            names = [f"{mod}.{a.name}" if f"{mod}.{a.name}" in known else mod for a in node.names]
        for name in names:
            while name and name not in known:
                name = name.rpartition(".")[0]
            if name and name != module:
                out.add(name)
    return out


def import_graph() -> dict[str, set[str]]:
    paths = [p for pkg in PACKAGES for p in (ROOT / pkg).rglob("*.py")]
    known = {module_name(p) for p in paths}
    return {module_name(p): imports_of(p, module_name(p), known) for p in paths}


def upward_imports(graph: dict[str, set[str]]) -> list[str]:
    bad = []
    for mod, targets in graph.items():
        (house, rank) = floor_of(mod)
        for t in targets:
            (t_house, t_rank) = floor_of(t)
            if t_rank > rank:
                bad.append(f"{mod} imports {t} (floor {t_house} is above {house})")
            elif t_rank == rank and frozenset({house, t_house}) in SIBLINGS:
                bad.append(f"{mod} imports {t} ({house} and {t_house} are siblings)")
    return sorted(bad)


def circles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components of more than one module (Tarjan, iterative)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[list[str]] = []
    counter = 0
    for root in sorted(graph):
        if root in index:
            continue
        work = [(root, iter(sorted(graph.get(root, ()))))]
        index[root] = low[root] = counter
        counter += 1
        stack.append(root)
        on_stack.add(root)
        while work:
            v, it = work[-1]
            for w in it:
                if w not in index:
                    index[w] = low[w] = counter
                    counter += 1
                    stack.append(w)
                    on_stack.add(w)
                    work.append((w, iter(sorted(graph.get(w, ())))))
                    break
                if w in on_stack:
                    low[v] = min(low[v], index[w])
            else:
                work.pop()
                if work:
                    low[work[-1][0]] = min(low[work[-1][0]], low[v])
                if low[v] == index[v]:
                    comp = []
                    while True:
                        w = stack.pop()
                        on_stack.discard(w)
                        comp.append(w)
                        if w == v:
                            break
                    if len(comp) > 1:
                        found.append(sorted(comp))
    return found


def test_no_upward_import():
    assert upward_imports(import_graph()) == []


def test_no_import_circle():
    assert circles(import_graph()) == []


def web_imports_of_station(graph: dict[str, set[str]]) -> list[str]:
    """Every module under station/ that imports a module of web/, with what it imports."""
    def under(module: str, package: str) -> bool:
        return module == package or module.startswith(package + ".")

    return sorted(f"{mod} imports {t}" for mod, targets in graph.items() if under(mod, "station")
                  for t in targets if under(t, "web"))


def test_station_never_imports_web():
    """The daemon runs without the web: the web app reads the station and the command line (cli/)
    starts both. A lazy import inside a function counts too."""
    bad = web_imports_of_station(import_graph())
    assert not bad, "station/ imports web/: " + "; ".join(bad)


def test_every_module_has_a_floor():
    assert [m for m in import_graph() if floor_of(m)[1] < 0] == []


def test_the_check_can_fail():
    """The checker itself finds an upward arrow, a sibling arrow and a circle (so the two tests
    above cannot pass by finding nothing)."""
    graph = {
        "contracts.types": {"station.daemon.supervisor"},  # ground floor reaching up
        "drivers.base": {"db.models"},  # sibling
        "station.science.sfem": {"station.decisions.verdicts"},  # pure science reaching up
        "db.writer": {"db.repository"},
        "db.repository": {"db.writer"},  # a circle
        "station.daemon.supervisor": {"contracts.types", "drivers.base", "db.writer"},
        "station.decisions.verdicts": set(),
        "db.models": set(),
    }
    bad = upward_imports(graph)
    assert any(b.startswith("contracts.types imports station.daemon.supervisor") for b in bad)
    assert any(b.startswith("drivers.base imports db.models") for b in bad)
    assert any(b.startswith("station.science.sfem imports station.decisions.verdicts") for b in bad)
    assert not any(b.startswith("station.daemon.supervisor") for b in bad)
    assert web_imports_of_station({"station.daemon.supervisor": {"web.app", "contracts.types"},
                                   "station.records.spc": set(), "cli.main": {"web.server"},
                                   "web.server": {"station.daemon.heap"}}) == [
        "station.daemon.supervisor imports web.app"]
    # the upward arrow above also closes a circle with the supervisor's own import
    assert sorted(circles(graph)) == [["contracts.types", "station.daemon.supervisor"], ["db.repository", "db.writer"]]
