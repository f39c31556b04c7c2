"""The package's layers (docs/design.md): what each subpackage may import, the core's subpackages and
their order (no import back up), no import cycles (hidden behind a registry string or not), and a
short longest import chain. Read from the source with ``ast``
(every import, function-local ones included), so nothing is run."""

import ast
from functools import cache
from pathlib import Path

PKG = Path(__file__).resolve().parents[1] / "lerobot_formation"
NAME = "lerobot_formation"

# layer -> the layers of ours it may import (its own always)
ALLOWED = {
    "core": set(),
    "compat": {"core"},
    "envs": {"core", "compat"},
    "policy": {"core", "compat", "threads"},
    "data": {"core", "compat", "envs", "threads"},
    "bench": {"core", "compat", "envs", "policy", "data", "threads"},
    "plugin": {"envs", "policy"},
    "with_plugin": set(),  # runs a LeRobot console script with the plugin loaded (through its shim)
    "threads": set(),
}
FOREIGN = {  # third-party packages a layer must not import
    "core": {"torch", "lerobot", "gymnasium", "diffusers", "datasets", "matplotlib"},
    "envs": {"diffusers"},
}
# The core's subpackages, lowest first: a module imports only its own subpackage and those below it.
CORE_FLOORS = ("world", "encodings", "perception", "controllers", "safety", "episodes")
ENGINE = ("bench.evaluation", "bench.controllers", "bench.diffusion_controller")
REPORTS = ("bench.results", "bench.paper_tables", "bench.figures", "bench.plots")
MAX_CHAIN = 7  # modules of ours, the numpy core counted as one (its own layering is core's business)


def module_name(path: Path) -> str:
    parts = path.relative_to(PKG).with_suffix("").parts
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(parts)


@cache
def modules() -> dict[str, Path]:
    return {module_name(p): p for p in PKG.rglob("*.py")}


def imports(name: str) -> set[str]:
    """Everything ``name`` imports: our modules without the package prefix, others by top-level name;
    "module:attr" registry strings of ours count as imports."""
    path = modules()[name]
    tree = ast.parse(path.read_text())
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    found = set()
    typing_only = {  # ``if TYPE_CHECKING:`` blocks import for annotations only, not at run time
        id(n)
        for block in ast.walk(tree)
        if isinstance(block, ast.If) and ast.unparse(block.test) == "TYPE_CHECKING"
        for stmt in block.body
        for n in ast.walk(stmt)
    }
    for node in ast.walk(tree):
        if id(node) in typing_only:
            continue
        targets = []
        if isinstance(node, ast.Import):
            targets = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = ".".join(
                    ([NAME] + package.split(".") if package else [NAME])[
                        : len(package.split(".")) + 2 - node.level
                    ]
                )
                mod = f"{base}.{node.module}" if node.module else base
            else:
                mod = node.module or ""
            targets = [mod] + [f"{mod}.{a.name}" for a in node.names]
        elif (
            isinstance(node, ast.Constant)
            and isinstance(node.value, str)
            and node.value.startswith(NAME + ".")
        ):
            targets = [node.value.partition(":")[0]]
        for t in targets:
            if t == NAME or t.startswith(NAME + "."):
                ours = t[len(NAME) + 1 :]
                if ours in modules():
                    found.add(ours)
            elif not t.startswith("."):
                found.add("!" + t.split(".")[0])
    found.discard(name)
    return found


def layer(name: str) -> str:
    return name.split(".")[0] if name else "__init__"


def test_each_layer_imports_only_what_it_may():
    wrong = []
    for name in modules():
        if not name:
            continue
        own = layer(name)
        for dep in imports(name):
            if dep.startswith("!"):
                if dep[1:] in FOREIGN.get(own, ()):
                    wrong.append(f"{name} -> {dep[1:]}")
            elif layer(dep) != own and layer(dep) not in ALLOWED[own]:
                wrong.append(f"{name} -> {dep}")
    assert not wrong, wrong


def core_floor(name: str) -> int:
    """The floor of a core module: its subpackage's place in ``CORE_FLOORS``."""
    return CORE_FLOORS.index(name.split(".")[1])


def test_the_core_is_its_subpackages():
    """Every module of the core but its package face (``core/__init__.py``) lives in one of the
    subpackages of ``CORE_FLOORS``, and each of them holds modules."""
    core = [m for m in modules() if layer(m) == "core" and m != "core"]
    stray = [m for m in core if m.split(".")[1] not in CORE_FLOORS]
    assert not stray, f"core modules outside {CORE_FLOORS}: {stray}"
    assert {m.split(".")[1] for m in core if m.count(".") == 2} == set(CORE_FLOORS)


def test_no_import_back_up_inside_the_core():
    """A core module imports its own subpackage and lower ones only (world < encodings < perception <
    controllers < safety < episodes), registry strings and function-local imports included; nothing
    in the core imports its package face."""
    wrong = []
    for name in modules():
        if layer(name) != "core" or name == "core":
            continue
        for dep in imports(name):
            if dep.startswith("!") or layer(dep) != "core":
                continue
            if dep == "core" or core_floor(dep) > core_floor(name):
                wrong.append(f"{name} -> {dep}")
    assert not wrong, wrong


def test_the_engine_imports_no_report_module():
    wrong = [
        f"{e} -> {d}"
        for e in ENGINE
        for d in imports(e)
        if any(d == r or d.startswith(r + ".") for r in REPORTS)
    ]
    assert not wrong, wrong


def test_the_package_root_imports_nothing_heavy():
    """``import lerobot_formation.core`` runs the package's __init__ first: it must stay empty of
    torch, LeRobot and gymnasium (the env registers itself in ``envs``)."""
    assert not {d for d in imports("") if d.startswith("!")}


def _graph() -> dict[str, set[str]]:
    """Our modules and their imports, the core as one node "core"."""

    def node(m: str) -> str:
        return "core" if layer(m) == "core" else m

    graph: dict[str, set[str]] = {}
    for m in modules():
        deps = {node(d) for d in imports(m) if not d.startswith("!")} - {node(m)}
        graph.setdefault(node(m), set()).update(deps)
    return graph


def test_the_core_has_no_cycle_inside():
    graph = {m: {d for d in imports(m) if layer(d) == "core"} for m in modules() if layer(m) == "core"}
    done: set[str] = set()

    def visit(m: str, path: list[str]) -> None:
        assert m not in path, f"import cycle: {' -> '.join(path[path.index(m) :] + [m])}"
        if m in done:
            return
        for d in graph[m]:
            visit(d, [*path, m])
        done.add(m)

    for m in graph:
        visit(m, [])


def test_no_import_cycles_and_a_short_longest_chain():
    graph = _graph()
    longest: dict[str, list[str]] = {}
    visiting: list[str] = []

    def chain(m: str) -> list[str]:
        if m in longest:
            return longest[m]
        assert m not in visiting, f"import cycle: {' -> '.join(visiting[visiting.index(m) :] + [m])}"
        visiting.append(m)
        best = max((chain(d) for d in graph[m]), key=len, default=[])
        visiting.pop()
        longest[m] = [m, *best]
        return longest[m]

    worst = max((chain(m) for m in graph), key=len)
    assert len(worst) <= MAX_CHAIN, f"{len(worst)} modules: {' -> '.join(worst)}"


def test_the_checker_sees_imports():
    """Not vacuous: the graph holds the arrows it must (a function-local import and a registry string)."""
    assert "core.world.dynamics" in imports("core.episodes.rollout")
    assert "policy.replanner" in imports("policy.modeling_formation_diffusion")
    assert "core.encodings.route_encoding" in imports("core.encodings.obstacle_grid")  # the registry string
    assert "core.controllers.protocol" in imports("core.controllers.mppi")  # function-local


def test_the_safety_layer_is_one_unit_of_the_core():
    """The replanner calls the safety layer (``core.safety.layer``), none of its insides; the layer is
    NumPy only and imports nothing above the core; the layer's baselines around route pursuit
    (``bench.layer_controller``) read no checkpoint."""
    assert "core.safety.layer" in imports("policy.replanner")
    insides = {
        "core.safety.guidance",
        "core.perception.obstacle_filter",
        "core.perception.obstacle_tracker",
        "core.controllers.route_pursuit",
    }
    assert not insides & imports("policy.replanner")
    deps = imports("core.safety.layer")
    assert all(layer(d) == "core" for d in deps if not d.startswith("!"))
    assert not {d[1:] for d in deps if d.startswith("!")} & FOREIGN["core"]
    assert not {"policy.checkpoint", "policy.modeling_formation_diffusion"} & imports(
        "bench.layer_controller"
    )


# test folders that are not a part of the package: the repository's scripts, the dataset scripts, the
# shared fixture files
OUTSIDE_THE_PACKAGE = {"scripts", "datasets", "fixtures"}


def test_the_tests_mirror_the_package():
    """Each folder of tests/ names a subpackage or module of the package (tests/core/<floor>/ a floor of
    the core), or one of OUTSIDE_THE_PACKAGE; the tests of the repository as a whole sit at the top."""
    tests = Path(__file__).resolve().parent
    for folder in sorted(p for p in tests.rglob("*") if p.is_dir() and p.name != "__pycache__"):
        part = folder.relative_to(tests)
        if part.parts[0] in OUTSIDE_THE_PACKAGE:
            continue
        target = PKG.joinpath(*part.parts)
        assert target.is_dir() or target.with_suffix(".py").is_file(), (
            f"tests/{part.as_posix()} names no part of lerobot_formation (move its tests where they belong)"
        )
    assert {p.name for p in (tests / "core").iterdir() if p.is_dir() and p.name != "__pycache__"} == set(
        CORE_FLOORS
    )
