"""The house (DESIGN.md): imports point one way, downwards, and never in a circle.

Every module of the six packages is read as source (``ast``, nothing imported), with every import it makes,
at its top or inside a function, resolved to the project's module it names. Four rules:

(a) No circle between modules. An import under ``if TYPE_CHECKING:`` never runs, so it closes no circle at
    import or run time; it still counts for (b)–(d): a type from above is knowledge of what is above.
(b) No import from a lower layer to a higher one. The packages, lowest first: models (the robot as
    mathematics) < acquisition (hardware → MCAP) < twin (the lab on a computer, speaking acquisition's
    wire protocols) < pipeline (MCAP → datasets → models) < analysis (figures) < vslab (the command line).
    Inside acquisition, lowest first, as its modules use each other:
    0. ``errors``, ``code_version``, ``processes``: leaves (the error base, the code's version, OS
       scheduling), importing nothing of acquisition but ``errors``;
    1. ``storage``: the lab's files on a path or a store;
    2. ``schemas`` (topics, messages, the session format: the contract between recorder and pipeline) and
       ``codecs`` (the devices' wire formats): data, with no behaviour of the lab;
    3. ``devices`` (drivers over the codecs) and ``command_guard`` (each outgoing command held to the
       robot's limits, which the drivers' daemons apply);
    4. ``safety``: a plan's and a measured state's limits, which the runners call;
    5. ``recorder``: the device daemons, the writer and the supervisor, over devices, guard and schemas;
    6. ``plans``: experiments as data and the runners that play them on the recorder's devices.
    A module may import its own rank or a lower one.
(c) Nothing under acquisition/ imports the twin (the drivers cannot tell an emulator from hardware).
(d) The pipeline reaches into acquisition only through what acquisition exposes at its level (the
    schemas, the storage, the errors, the code version, and the plans whose compensation hook it fills);
    analysis reaches acquisition only through the pipeline.
"""

from __future__ import annotations

import ast
from functools import cache
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
LAYERS = ("models", "acquisition", "twin", "pipeline", "analysis", "vslab")
ACQUISITION_RANK = {  # by the longest dotted prefix under acquisition/
    "errors": 0, "code_version": 0, "processes": 0, "storage": 1, "schemas": 2, "codecs": 2, "devices": 3,
    "command_guard": 3, "safety": 4, "recorder": 5, "plans": 6,
    # bringing devices up (issue 31): probes over the codecs and the bus budget, below the recorder
    "bringup": 4,
    # the device-kind registry (issue 30): a leaf that names drivers, sources and emulators by strings,
    # imported when used; the schemas and the pipeline consult it
    "devices.kinds": 0,
}  # fmt: skip
REACHABLE = {  # (d): what of acquisition each higher package may import, by dotted prefix
    # recorder.sessions: the store of a lab's recorded sessions (list, read, publish, recover), the Lab's
    # ``sessions``: acquisition's face to the pipeline for what it recorded
    "pipeline": {
        "schemas",
        "storage",
        "errors",
        "code_version",
        "plans",
        "devices.kinds",
        "recorder.sessions",
    },
    "analysis": set(),
}
# Pairs (importer, imported) allowed to break a rule for now, each named exactly so a new one fails.
KNOWN: set[tuple[str, str]] = set()  # none left: issue 30 fixed every pair


def _under(module: str, keys) -> str | None:
    """The longest of ``keys`` that ``module`` (``acquisition.…``) is, or lies in."""
    parts = module.split(".")[1:]
    for n in range(len(parts), 0, -1):
        if ".".join(parts[:n]) in keys:
            return ".".join(parts[:n])
    return None


def _module_files() -> dict[str, Path]:
    """Every module of the six packages: dotted name → file (a package is its ``__init__``)."""
    out = {}
    for package in LAYERS:
        for file in sorted((ROOT / package).rglob("*.py")):
            parts = list(file.relative_to(ROOT).with_suffix("").parts)
            out[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = file
    return out


MODULES = _module_files()


def _known_module(name: str) -> str | None:
    """The project's module ``name`` is, or lies in (``a.b.c`` → ``a.b`` when c is a name in a.b)."""
    while name and name not in MODULES:
        name = name.rpartition(".")[0]
    return name or None


def _type_checking_nodes(tree: ast.AST) -> set[int]:
    """The ids of the import nodes under ``if TYPE_CHECKING:`` (never run)."""
    out = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.If) and "TYPE_CHECKING" in ast.unparse(node.test):
            out |= {id(n) for stmt in node.body for n in ast.walk(stmt)}
    return out


@cache
def imports(module: str) -> dict[str, bool]:
    """The project's modules ``module`` imports anywhere in its source → whether the import runs (False:
    only under ``if TYPE_CHECKING:``)."""
    file = MODULES[module]
    tree = ast.parse(file.read_text(encoding="utf-8"), str(file))
    typing_only = _type_checking_nodes(tree)
    package = module if file.name == "__init__.py" else module.rpartition(".")[0]
    out: dict[str, bool] = {}
    for node in ast.walk(tree):
        names: list[str] = []
        if isinstance(node, ast.Import):
            names = [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:  # relative: from the package, one level up per extra dot
                anchor = package
                for _ in range(node.level - 1):
                    anchor = anchor.rpartition(".")[0]
                base = f"{anchor}.{base}" if base else anchor
            names = [f"{base}.{alias.name}" for alias in node.names]  # a submodule, or a name in base
        for name in names:
            target = _known_module(name)
            if target is not None and target != module:
                out[target] = out.get(target, False) or id(node) not in typing_only
    return out


def _layer(module: str) -> int:
    return LAYERS.index(module.split(".")[0])


def _acquisition_rank(module: str) -> int | None:
    key = _under(module, ACQUISITION_RANK) if module.startswith("acquisition.") else None
    return None if key is None else ACQUISITION_RANK[key]


def _edges() -> list[tuple[str, str]]:
    return [(a, b) for a in MODULES for b in imports(a)]


def _circles() -> list[list[str]]:
    """The strongly connected groups of more than one module in the graph of imports that run (Tarjan)."""
    graph = {m: [t for t, runs in imports(m).items() if runs] for m in MODULES}
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in graph[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            group = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                group.append(w)
                if w == v:
                    break
            if len(group) > 1:
                found.append(sorted(group))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return found


def _upward(a: str, b: str) -> bool:
    """Does ``a`` importing ``b`` point upwards (b)?"""
    if _layer(b) != _layer(a):
        return _layer(b) > _layer(a)
    ra, rb = _acquisition_rank(a), _acquisition_rank(b)
    return ra is not None and rb is not None and rb > ra


def _into_twin(a: str, b: str) -> bool:
    """Does ``a`` import the twin from acquisition (c)?"""
    return a.split(".")[0] == "acquisition" and b.split(".")[0] == "twin"


def _unreachable(a: str, b: str) -> bool:
    """Does ``a`` reach into acquisition below what its package may import (d)?"""
    top = a.split(".")[0]
    return top in REACHABLE and b.split(".")[0] == "acquisition" and _under(b, REACHABLE[top]) is None


def test_the_scan_reads_every_package_and_the_imports_inside_functions():
    assert {m.split(".")[0] for m in MODULES} == set(LAYERS)
    assert all(_acquisition_rank(m) is not None for m in MODULES if m.startswith("acquisition."))
    # vslab/recording.py imports the plan runner inside its command, not at its top
    assert imports("vslab.recording").get("acquisition.plans.plan_run") is True
    assert imports("twin.runner")["acquisition.plans.compensation"] is True


def test_the_rules_catch_what_they_forbid():
    """Each rule fails on a pair that breaks it (a rule that cannot fail checks nothing)."""
    assert _upward("acquisition.safety", "acquisition.plans.plan")
    assert _upward("models.robot", "acquisition.errors")
    assert _upward("twin.rig", "pipeline.in_loop")
    assert not _upward("acquisition.plans.rt_runner", "acquisition.safety")
    assert _into_twin("acquisition.recorder.sources", "twin.ptyhost")
    assert not _into_twin("twin.rig_process", "acquisition.recorder.setup")
    assert _unreachable("pipeline.session_index", "acquisition.recorder.recorder")
    assert _unreachable("analysis.popup_tests", "acquisition.schemas.events")
    assert not _unreachable("pipeline.ingest", "acquisition.schemas.topics")
    assert _unreachable("pipeline.clean", "acquisition.devices.servo_bus")
    assert not _unreachable("pipeline.clean", "acquisition.devices.kinds")
    assert _upward("acquisition.schemas.topics", "acquisition.devices.servo_bus")
    assert not _upward("acquisition.schemas.topics", "acquisition.devices.kinds")


def test_no_import_circle():
    assert _circles() == []


@pytest.mark.parametrize("rule", ["downwards", "acquisition without the twin", "through what is exposed"])
def test_imports_point_downwards(rule):
    check = {"downwards": _upward, "acquisition without the twin": _into_twin,
             "through what is exposed": _unreachable}[rule]  # fmt: skip
    broken = sorted((a, b) for a, b in _edges() if check(a, b))
    assert [p for p in broken if p not in KNOWN] == [], f"{rule}: importer → imported"


def test_every_known_pair_still_breaks_a_rule():
    """A pair fixed leaves the list, so it never excuses a new import."""
    edges = set(_edges())
    here = [p for p in KNOWN if p[0] in MODULES]
    stale = [p for p in here if p not in edges or not (_upward(*p) or _into_twin(*p) or _unreachable(*p))]
    assert stale == []
