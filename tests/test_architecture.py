"""The layout of docs/architecture.md, checked on the source: layers, import cycles, where names are defined, and
that every citation resolves inside the repository.

The import graph is read with ``ast`` from every module of the package (imports inside functions included); the
same check runs from the command line: ``python tests/test_architecture.py``.
"""

from __future__ import annotations

import ast
import os
import pathlib
import re
import subprocess
import sys

ROOT = pathlib.Path(__file__).resolve().parents[1]
PACKAGE = ROOT / "cpgjax"

# docs/architecture.md: the layers, lowest first. A module may import modules of its own layer or of lower ones.
LAYERS = (
    (
        "run provenance, output files, flat layouts, JAX internals, compile cache",
        ("provenance", "outputs", "layout", "jax_internals", "compile_cache"),
    ),
    (
        "go1 facts",
        ("go1.constants", "go1.kinematics", "go1.attitude", "go1.physics", "go1.terrain", "go1.model", "go1.sensors"),
    ),
    ("parameters and GP", ("trial.params", "gp")),
    ("controller", ("cpg",)),
    ("trial", ("trial.limits", "trial.protocol", "trial.objective", "trial.tuned", "trial.condition")),
    ("optimizer", ("optim.acquisition", "optim.exploration", "optim.config", "optim.bo", "optim.black_box")),
    ("optimizer setting", ("trial.optimizer_setting",)),
    (
        "simulation",
        ("sim.base", "mjx_go1", "sim.native", "sim.native_physics", "sim.ffi_step", "sim.backends", "sim.walk"),
    ),
    (
        "study definitions and files",
        ("study.spec", "study.scene", "study.placement", "study.batch", "study.files", "study.rate"),
    ),
    ("the study engine", ("ablation",)),
    (
        "studies",
        (
            "studies.stats",
            "studies.renderer",
            "studies.video",
            "studies.viewer",
            "studies.figures",
            "studies.registry",
            "studies.gaits",
            "studies.generic",
            "studies.transfer",
            "studies.options",
            "studies.optimize",
            "studies.driver",
            "studies.launch",
        ),
    ),
    (
        "robot",
        (
            "robot.wire",
            "robot.transport",
            "robot.cpu_dispatch",
            "robot.memory_lock",
            "robot.cpu_wakeup",
            "robot.foot_force",
            "robot.safety",
            "robot.controller",
            "robot.sim_server",
        ),
    ),
    ("the 1 kHz loop", ("hardware_io",)),
    (
        "deployment",
        ("deployment.options", "deployment.tick_log", "deployment.trials", "deployment.deploy", "deployment.calibrate"),
    ),
    ("command line", ("cli", "show")),
)
# The design's modules, the entry point and its results browser, and below every layer what a run records about its
# code and machine, the entry type of the catalogue of output files, how a pytree is laid out in a flat vector, the
# one module that reads JAX's internals, and where compiled code is kept
TOP_LEVEL = {
    "cpg",
    "gp",
    "mjx_go1",
    "ablation",
    "hardware_io",
    "cli",
    "show",  # the entry point and its results browser
    "provenance",
    "outputs",
    "layout",
    "jax_internals",
    "compile_cache",
}
# docs/architecture.md: these layers sit side by side, neither imports the other (whatever their order in LAYERS).
SIDE_BY_SIDE = tuple(
    (a, b)
    for a in ("study definitions and files", "the study engine", "studies")
    for b in ("robot", "the 1 kHz loop", "deployment")
)
# docs/architecture.md: the optimizer is generic over its parameter and context boxes; of cpgjax it imports only these
# (and its own modules), never the robot's facts or the trial.
OPTIMIZER_IMPORTS = {"gp"}


def module_files() -> dict[str, pathlib.Path]:
    """Dotted module name below ``cpgjax`` (``""`` for the package) → file."""
    out = {}
    for path in sorted(PACKAGE.rglob("*.py")):
        parts = path.relative_to(PACKAGE).with_suffix("").parts
        out[".".join(p for p in parts if p != "__init__")] = path
    return out


def _resolve(name: str, modules) -> str | None:
    """The cpgjax module a dotted import target names (a name imported from a module counts as that module)."""
    if name == "cpgjax":
        return ""
    if not name.startswith("cpgjax."):
        return None
    name = name[len("cpgjax.") :]
    while name and name not in modules:
        name = name.rpartition(".")[0]
    return name


def import_graph() -> dict[str, set[str]]:
    """Module → the cpgjax modules it imports (at any depth of the file)."""
    modules = module_files()
    graph = {}
    for name, path in modules.items():
        edges = set()
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Import):
                targets = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
                targets = [f"{node.module}.{a.name}" for a in node.names]
            else:
                continue
            edges |= {t for t in (_resolve(x, modules) for x in targets) if t is not None and t != name}
        graph[name] = edges - {""}
    return graph


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Every strongly connected component of more than one module (Tarjan)."""
    index, low, stack, on_stack, found = {}, {}, [], set(), []

    def visit(v):
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in graph.get(v, ()):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                found.append(sorted(component))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return found


def layer_of() -> dict[str, int]:
    return {module: rank for rank, (_, members) in enumerate(LAYERS) for module in members}


def test_every_module_has_a_layer():
    modules = {m for m in module_files() if m}
    packages = {m for m in modules if (PACKAGE / m.replace(".", "/") / "__init__.py").exists()}
    modules -= packages
    assert sorted(modules - set(layer_of())) == []
    assert sorted(set(layer_of()) - modules) == []


def test_top_level_holds_the_design_modules_only():
    top = {p.stem for p in PACKAGE.glob("*.py")} - {"__init__"}
    assert top == TOP_LEVEL


def test_no_import_cycles():
    assert cycles(import_graph()) == []


def test_lower_layers_never_import_higher_ones():
    rank = layer_of()
    upward = [
        f"{a} ({LAYERS[rank[a]][0]}) imports {b} ({LAYERS[rank[b]][0]})"
        for a, targets in import_graph().items()
        if a in rank
        for b in sorted(targets)
        if b in rank and rank[b] > rank[a]
    ]
    assert upward == []


def test_the_robot_and_the_studies_never_import_each_other():
    members = dict(LAYERS)
    crossing = []
    for pair in SIDE_BY_SIDE:
        one, other = (set(members[name]) for name in pair)
        crossing += [
            f"{a} imports {b}"
            for a, targets in import_graph().items()
            for b in sorted(targets)
            if (a in one and b in other) or (a in other and b in one)
        ]
    assert crossing == []


def test_the_optimizer_imports_nothing_of_the_robot_or_the_trial():
    robot_side = [
        f"{a} imports {b}"
        for a, targets in import_graph().items()
        if a.startswith("optim.")
        for b in sorted(targets)
        if not b.startswith("optim.") and b not in OPTIMIZER_IMPORTS
    ]
    assert robot_side == []


def test_every_module_imports_in_a_fresh_interpreter():
    names = [f"cpgjax.{m}" if m else "cpgjax" for m in module_files()]
    code = f"import importlib\nfor n in {names!r}:\n    importlib.import_module(n)\nprint('ok')"
    out = subprocess.run(
        [sys.executable, "-c", code],
        capture_output=True,
        text=True,
        timeout=300,
        cwd=ROOT,
        env={"JAX_PLATFORMS": "cpu", "PATH": "/usr/bin:/bin"},
    )
    assert out.returncode == 0 and out.stdout.strip().endswith("ok"), out.stderr[-2000:]


def _defined_names(path: pathlib.Path) -> set[str]:
    """Names a module binds at its top level (functions, classes, assignments, and imports of other libraries), not
    the names it imports from cpgjax: those are somebody else's."""
    names = set()
    for node in ast.parse(path.read_text()).body:
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
            names.add(node.name)
        elif isinstance(node, (ast.Assign, ast.AnnAssign, ast.AugAssign)):
            for target in node.targets if isinstance(node, ast.Assign) else [node.target]:
                names |= {n.id for n in ast.walk(target) if isinstance(n, ast.Name)}
        elif isinstance(node, ast.Import):
            names |= {(a.asname or a.name).split(".")[0] for a in node.names if not a.name.startswith("cpgjax")}
        elif isinstance(node, ast.ImportFrom) and not (node.module or "").startswith("cpgjax"):
            names |= {a.asname or a.name for a in node.names}
    return names


def _source_files():
    for folder in ("cpgjax", "tests", "benchmarks", "studies"):
        yield from sorted((ROOT / folder).rglob("*.py"))


def test_names_are_used_from_the_module_that_defines_them():
    """No re-export: ``from cpgjax.m import name`` and ``alias.name`` (alias bound to a cpgjax module) name something
    ``m`` itself defines, or one of its submodules."""
    modules = module_files()
    defined = {m: _defined_names(p) for m, p in modules.items()}
    wrong = []
    for path in _source_files():
        tree = ast.parse(path.read_text())
        aliases = {}
        for node in ast.walk(tree):
            if (
                isinstance(node, ast.ImportFrom)
                and node.module
                and node.module.startswith("cpgjax")
                and node.level == 0
            ):
                source = _resolve(node.module, modules)
                for a in node.names:
                    sub = f"{source}.{a.name}" if source else a.name
                    if sub in modules:
                        aliases[a.asname or a.name] = sub
                    elif a.name not in defined[source]:
                        wrong.append(f"{path.relative_to(ROOT)}:{node.lineno} imports {a.name} from cpgjax.{source}")
        for node in ast.walk(tree):
            if isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name) and node.value.id in aliases:
                module = aliases[node.value.id]
                if node.attr not in defined[module] and f"{module}.{node.attr}" not in modules:
                    wrong.append(
                        f"{path.relative_to(ROOT)}:{node.lineno} uses {node.value.id}.{node.attr}, "
                        f"not defined in cpgjax.{module}"
                    )
    assert wrong == []


# A citation of the project's own record: docs/<file>.md, optionally followed by §<number>.
_DOC_CITATION = re.compile(r"docs/([\w.-]+\.md)(?:\s*§\s*(\d+(?:\.\d+)?))?")
# The brief's file names, which exist only outside the repository.
_OUTSIDE = re.compile(
    r"(?<![\w/])(?:decisions|go1-sdk|go1-model|controller|bayesopt|mjx-and-style)\.md|paper\.tex"
    r"|\.\./shared"
)


def _cited_files():
    yield from _source_files()
    yield from sorted((ROOT / "docs").glob("*.md"))
    yield ROOT / "README.md"
    yield ROOT / "benchmarks" / "RESULTS.md"


def _sections(doc: pathlib.Path) -> set[str]:
    return set(re.findall(r"^#+ .*?§\s*(\d+(?:\.\d+)?)", doc.read_text(), flags=re.M))


def test_every_citation_resolves_inside_the_repository():
    problems = []
    for path in _cited_files():
        text = path.read_text()
        in_docs = path.parent == ROOT / "docs"
        for m in _DOC_CITATION.finditer(text):
            doc = ROOT / "docs" / m.group(1)
            if not doc.exists():
                problems.append(f"{path.relative_to(ROOT)}: {m.group(0)} (no such file)")
            elif m.group(2) and m.group(2) not in _sections(doc):
                problems.append(f"{path.relative_to(ROOT)}: {m.group(0)} (no such section)")
        for m in _OUTSIDE.finditer(text):
            name = m.group(0)
            # inside docs/, a bare sibling name is a relative link to the file beside it
            if in_docs and name.endswith(".md") and (ROOT / "docs" / name).exists():
                continue
            problems.append(f"{path.relative_to(ROOT)}: cites {name}, which is not in the repository")
    assert problems == []


# The control tick's one home (CONTROL_HZ, TICK_S, ticks, seconds): anywhere else a literal 1000 or 0.001 is a tick
# conversion written out, unless it is one of these, each (module, the function or class it is in, value) → what it is.
TICK_HOME = "go1/constants.py"
NOT_TICKS = {
    ("study/placement.py", "exchange", 1000): "the key-value store's wait in milliseconds",
    ("go1/physics.py", "<module>", 0.001): "MuJoCo's solimp width and the feet's 1 mm contact layer",
    ("hardware_io.py", "timing_table", 1000): "µs in a table as a fraction of the period",
    ("hardware_io.py", "_enter_realtime", 1000): "the kernel's µs in a message as ms",
    ("robot/foot_force.py", "<module>", 0.001): "the lowest N per count a calibration accepts",
    ("robot/sim_server.py", "motor_torque", 1000): "the distance from the SDK's stop sentinel that marks it",
    ("robot/sim_server.py", "SimGo1Server._tick_once", 1000): "an injected fault's delay in ms as s",
    ("sim/ffi_step.py", "Stepper.__init__", 1000): "the size of the native step's error message buffer",
    ("study/spec.py", "<module>", 1000): "the longest ramp a study file may give, in m",
    ("trial/limits.py", "<module>", 1000): "the most trials a run may ask for",
}


def _tick_literals(path: pathlib.Path):
    """(scope, value, line) of each literal 1000 or 0.001 (any spelling: 1e3, 1000.0, 1e-3) in the file; scope is
    the dotted name of the function or class it is in, ``<module>`` at the top level."""
    found = []

    def visit(node, scope):
        for child in ast.iter_child_nodes(node):
            inner = scope
            if isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
                inner = f"{scope}.{child.name}" if scope else child.name
            if isinstance(child, ast.Constant) and type(child.value) in (int, float) and child.value in (1000, 0.001):
                found.append((scope or "<module>", child.value, child.lineno))
            visit(child, inner)

    visit(ast.parse(path.read_text()), "")
    return found


def test_ticks_are_converted_in_one_place():
    """Seconds ↔ control ticks through go1.constants alone: no other module writes 1000 or 0.001 except the listed
    uses that are not ticks, and every listed use still exists."""
    bare, seen = [], set()
    for path in sorted(PACKAGE.rglob("*.py")):
        name = str(path.relative_to(PACKAGE))
        if name == TICK_HOME:
            continue
        for scope, value, line in _tick_literals(path):
            key = (name, scope, 1000 if value == 1000 else 0.001)
            seen.add(key)
            if key not in NOT_TICKS:
                bare.append(f"cpgjax/{name}:{line} writes {value!r} in {scope} (go1.constants.ticks/seconds/TICK_S)")
    assert bare == []
    assert sorted(set(NOT_TICKS) - seen, key=str) == []


if __name__ == "__main__":
    graph = import_graph()
    print(f"{len(graph)} modules, {sum(map(len, graph.values()))} import arrows, cycles: {cycles(graph) or 'none'}")


def test_importing_cpgjax_runs_no_jax_computation():
    """Every module imports without a JAX computation, so JAX's CPU client does not exist yet and a process (the
    robot loop, the simulated Go1, a distributed study) can still choose its dispatch and devices after the imports:
    ``cpu_dispatch.request_inline`` then reports inline dispatch. An array built at import would create the client
    unpinned and asynchronous (it slowed the robot loop's step by half, benchmarks/hardware_loop.py)."""
    names = sorted(n for n in module_files() if n)
    code = (
        "import importlib, sys\n"
        f"for name in {names!r}:\n"
        "    importlib.import_module('cpgjax.' + name)\n"
        "from cpgjax.robot import cpu_dispatch\n"
        "print(cpu_dispatch.request_inline())\n"
    )
    out = subprocess.run(
        [sys.executable, "-c", code],
        capture_output=True,
        text=True,
        timeout=300,
        env={**os.environ, "JAX_PLATFORMS": "cpu"},
    )
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.strip().splitlines()[-1] == "True", out.stdout[-500:]


def test_only_jax_internals_reads_jax_internals():
    """``jax._src`` is imported by cpgjax/jax_internals.py alone (what JAX's public API does not give)."""
    readers = sorted(
        str(path.relative_to(ROOT))
        for name, path in module_files().items()
        if "jax._src" in path.read_text() and name != "jax_internals"
    )
    assert readers == []


def import_names() -> dict[str, set[str]]:
    """cpgjax module → the names the package's modules import it under (``from cpgjax.go1 import model as
    go1_model`` gives ``go1.model`` → ``go1_model``)."""
    modules = module_files()
    names: dict[str, set[str]] = {}
    for path in modules.values():
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom) and node.module and node.module.startswith("cpgjax") and not node.level:
                for alias in node.names:
                    target = f"{node.module}.{alias.name}".removeprefix("cpgjax.")
                    if target in modules:
                        names.setdefault(target, set()).add(alias.asname or alias.name)
    return names


def test_each_module_has_one_import_name():
    """docs/architecture.md, "Import names": a module is imported under one name across the package, its own or the
    alias the table there gives with its reason."""
    several = {module: sorted(n) for module, n in import_names().items() if len(n) > 1}
    assert several == {}
    table = (ROOT / "docs" / "architecture.md").read_text()
    documented = re.findall(r"^\| `([a-z0-9_.]+)` \| `([a-z0-9_]+)` \|", table, re.M)
    aliased = {module: next(iter(n)) for module, n in import_names().items() if next(iter(n)) != module.split(".")[-1]}
    assert aliased == dict(documented)


def test_folders_follow_the_layers():
    """A folder holds one layer: what the 1 kHz loop uses (robot/) sits below hardware_io.py, what drives it
    (deployment/) above; the study definitions and files (study/) below the study engine (ablation.py), the studies,
    their reports and launcher (studies/) above; every layer's modules share their folder (or sit at the top)."""
    folders = {name: {module.split(".")[0] if "." in module else "" for module in modules} for name, modules in LAYERS}
    assert folders["robot"] == {"robot"} and folders["deployment"] == {"deployment"}
    assert folders["the 1 kHz loop"] == {""} and folders["the study engine"] == {""}
    assert folders["study definitions and files"] == {"study"} and folders["studies"] == {"studies"}
    rank = {name: i for i, (name, _) in enumerate(LAYERS)}
    assert rank["robot"] < rank["the 1 kHz loop"] < rank["deployment"]
    assert rank["study definitions and files"] < rank["the study engine"] < rank["studies"]
    listed = {module for _, modules in LAYERS for module in modules}
    for folder in ("robot", "deployment", "study", "studies"):
        assert {m for m in module_files() if m.startswith(folder + ".")} <= listed


# Where a module's tests are (docs/architecture.md "Tests"): tests/<package>/test_<module>[_<topic>].py for a module of
# cpgjax/<package>/, tests/test_<module>[_<topic>].py for one at the top of the package, and
# tests/analyses/test_<script>[_<topic>].py for an analysis in studies/. These check the repository as a whole.
REPOSITORY_TESTS = {"test_architecture", "test_docs_commands", "test_readme"}


def test_tests_sit_by_the_module_they_test():
    modules = module_files()
    scripts = {p.stem for p in (ROOT / "studies").glob("*.py")}
    misplaced = []
    for path in sorted((ROOT / "tests").rglob("test_*.py")):
        folder = path.parent.relative_to(ROOT / "tests").as_posix()
        name = path.stem.removeprefix("test_")
        if folder == "." and path.stem in REPOSITORY_TESTS:
            continue
        if folder == "analyses":
            homes = scripts
        else:
            prefix = "" if folder == "." else folder.replace("/", ".") + "."
            homes = {
                m.removeprefix(prefix)
                for m in modules
                if m.startswith(prefix) and m and "." not in m.removeprefix(prefix)
            }
        if not any(name == home or name.startswith(home + "_") for home in homes):
            misplaced.append(str(path.relative_to(ROOT)))
    assert misplaced == []


# The design's five modules (docs/architecture.md): each public function states its contract in its docstring.
DESIGN_MODULES = ("cpg", "gp", "mjx_go1", "ablation", "hardware_io")


def _contract_gaps(function: ast.FunctionDef) -> list[str]:
    """The sections a public function's docstring lacks: Args (it takes parameters), Returns (it returns a value; a
    property's docstring says what it is), Raises (its body raises)."""
    doc = ast.get_docstring(function) or ""
    params = [
        a.arg
        for a in (*function.args.posonlyargs, *function.args.args, *function.args.kwonlyargs)
        if a.arg not in ("self", "cls")
    ]
    is_property = any(isinstance(d, ast.Name) and d.id == "property" for d in function.decorator_list)
    returns = (
        not is_property
        and function.returns is not None
        and not (isinstance(function.returns, ast.Constant) and function.returns.value is None)
    )
    raises = any(isinstance(node, ast.Raise) for node in ast.walk(function))
    return [
        section
        for section, needed in (("Args:", params), ("Returns:", returns), ("Raises:", raises))
        if needed and section not in doc
    ]


def test_the_design_modules_state_their_contracts():
    gaps = []
    for name in DESIGN_MODULES:
        tree = ast.parse((PACKAGE / f"{name}.py").read_text())
        for node in tree.body:
            members = (
                [node]
                if isinstance(node, ast.FunctionDef)
                else (
                    [n for n in node.body if isinstance(n, ast.FunctionDef)]
                    if isinstance(node, ast.ClassDef) and not node.name.startswith("_")
                    else []
                )
            )
            for function in members:
                if not function.name.startswith("_") and (missing := _contract_gaps(function)):
                    gaps.append(f"{name}.py:{function.lineno} {function.name}: {', '.join(missing)}")
    assert gaps == []
