"""The house: subpackages along the data path, one list of public names, no import cycle, small signatures."""

import ast
import inspect
from pathlib import Path

import numpy as np
import pytest

import sdp

SRC = Path(sdp.__file__).parent
#: Records that sdp makes and returns, not calls a user writes: their fields are what they report.
RECORDS = {"ChangeResult", "Distances", "Defaults", "FileComparison", "FileDistances", "ChangePlan",
           "FrameChange", "Region", "Alignment", "Mesh", "Cloud", "Grid"}


def _modules() -> dict[str, Path]:
    out = {}
    for path in SRC.rglob("*.py"):
        parts = path.relative_to(SRC.parent).with_suffix("").parts
        name = ".".join(parts[:-1] if parts[-1] == "__init__" else parts)
        out[name] = path
    return out


def _imports(name: str, path: Path, modules: dict[str, Path]) -> set[str]:
    """The sdp modules ``name`` imports, at any depth of its code (functions included); a package's
    ``__init__`` is left out (it imports nothing: lazy_loader reads its stub)."""
    package = name if path.name == "__init__.py" else name.rsplit(".", 1)[0]
    found = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")[: len(package.split(".")) - node.level + 1]
                target = ".".join(base + ([node.module] if node.module else []))
            else:
                target = node.module or ""
            for alias in node.names:
                candidate = f"{target}.{alias.name}"
                found.add(candidate if candidate in modules else target)
        elif isinstance(node, ast.Import):
            found.update(alias.name for alias in node.names)
    return {m for m in found if m in modules and m != name and modules[m].name != "__init__.py"}


def test_no_import_cycle_inside_sdp():
    modules = _modules()
    graph = {name: _imports(name, path, modules) for name, path in modules.items()}
    state, stack, cycles = {}, [], []

    def visit(u):
        state[u] = "open"
        stack.append(u)
        for v in sorted(graph[u]):
            if state.get(v) == "open":
                cycles.append(" -> ".join(stack[stack.index(v):] + [v]))
            elif v not in state:
                visit(v)
        stack.pop()
        state[u] = "done"

    for name in sorted(graph):
        if name not in state:
            visit(name)
    assert cycles == []
    assert graph["sdp.fields._lattice"] and graph["sdp.cli._change"]  # the walk sees imports at all


#: The subpackages in the order of docs/architecture.md's map: the data path.
PATH = ["io", "fields", "change", "distance", "registration", "stream", "scale", "timeseries", "viz", "actions",
        "cli", "data"]


def test_a_module_imports_at_its_top_only_the_stages_before_it():
    """docs/architecture.md: a later stage serving an earlier one is imported inside the function
    that needs it, so that importing a module never loads the stages after it."""
    rank = {p: i for i, p in enumerate(PATH)}
    late = []
    for name, path in _modules().items():
        own = name.split(".")[1] if name.count(".") else ""
        if own not in rank:
            continue
        for node in ast.parse(path.read_text()).body:  # the module's top level only
            if isinstance(node, ast.ImportFrom) and node.level == 2 and node.module:
                other = node.module.split(".")[0]
                if other in rank and rank[other] > rank[own]:
                    late.append(f"{name} imports {node.module}")
    assert late == []
    assert set(PATH) <= {p.name for p in SRC.iterdir() if (p / "__init__.py").exists()}


def test_the_top_level_reads_as_the_data_path():
    modules = sorted(p.name for p in SRC.glob("*.py"))
    packages = sorted(p.name for p in SRC.iterdir() if (p / "__init__.py").exists())
    assert len(modules) <= 8, modules
    assert {"io", "fields", "change", "distance", "registration", "stream", "scale", "viz", "cli"} <= set(packages)
    for package in packages:  # each subpackage declares its public surface in one stub
        assert (SRC / package / "__init__.pyi").exists(), package


def test_every_public_name_resolves_from_the_one_list():
    stub = ast.parse((SRC / "__init__.pyi").read_text())
    listed = {a.asname or a.name for n in stub.body if isinstance(n, ast.ImportFrom) for a in n.names}
    assert set(sdp.__all__) == listed
    for name in sdp.__all__:
        assert getattr(sdp, name) is not None, name
    assert sdp.align is sdp.registration.align  # a function, not hidden by a submodule
    assert type(sdp) is type(inspect)  # the package's class is not replaced


def _callables():
    for name in sdp.__all__:
        obj = getattr(sdp, name)
        if inspect.ismodule(obj) or not callable(obj) or inspect.isclass(obj) and issubclass(obj, BaseException):
            continue
        if inspect.isclass(obj):
            if name not in RECORDS:
                yield name, obj
            for attr, member in vars(obj).items():
                if not attr.startswith("_") and isinstance(member, (classmethod, staticmethod)) or (
                        not attr.startswith("_") and inspect.isfunction(member)):
                    yield f"{name}.{attr}", getattr(obj, attr)
        else:
            yield name, obj


@pytest.mark.parametrize("name, func", list(_callables()), ids=lambda v: v if isinstance(v, str) else "")
def test_no_public_callable_takes_more_than_13_parameters(name, func):
    """A concern with several parameters is one option object (:mod:`sdp.options`); the widest
    call, ``compare_files``, takes its inputs, output and topic and one object or value per concern."""
    params = [p for p in inspect.signature(func).parameters.values() if p.name not in ("self", "cls")]
    assert len(params) <= 13, f"{name}: {len(params)} parameters"


def test_options_are_shared_and_checked_once():
    lattice = sdp.Lattice(voxel_size=0.05)
    with pytest.raises(sdp.InvalidOptionError, match="voxel_size"):
        sdp.Lattice(voxel_size=0)
    with pytest.raises(sdp.InvalidOptionError, match="grid_size= or voxel_size=, not both"):
        sdp.Lattice(voxel_size=0.02, grid_size=80)  # refused when made, not by some callers only
    with pytest.raises(sdp.InvalidOptionError, match="range_noise"):
        sdp.Coverage(range_noise=-1)
    with pytest.raises(sdp.InvalidOptionError, match="workers"):
        sdp.Execution(workers=0)
    with pytest.raises(sdp.InvalidOptionError, match="density alignment only"):
        sdp.Registration(method="gicp", fix_horizontal=True)
    with pytest.raises(sdp.InvalidOptionError, match="projection_scale"):
        sdp.Cylinder(projection_scale=-1)
    with pytest.raises(sdp.InvalidOptionError, match="range_exponent"):
        sdp.NoiseModel(range_exponent=3)
    with pytest.raises(AttributeError):  # frozen
        lattice.voxel_size = 1
    pts = np.random.default_rng(0).random((200, 3))
    for call in (lambda: sdp.detect_changes(pts, pts, lattice={"voxel_size": 0.1}),  # a dict: one line, not an
                 lambda: sdp.distances(pts, pts, cylinder={"projection_scale": 0.2}),  # AttributeError inside
                 lambda: next(sdp.watch(pts, [pts], coverage={"sensor_origin": None}))):
        with pytest.raises(sdp.InvalidOptionError, match=r"must be an sdp\.(Lattice|Cylinder|Coverage)"):
            call()
    for func in (sdp.detect_changes, sdp.detect_changes_tiled, sdp.watch, sdp.compare_files, sdp.plan_change,
                 sdp.build_field_tiled):
        assert inspect.signature(func).parameters["lattice"].annotation in ("Lattice | None",)
    assert sdp.Registration().method == sdp.DEFAULTS.align_method
    # an output a command does not write is refused, not ignored (in Python as on the command line)
    for call, says in ((lambda: sdp.distance_files("a.npy", "b.npy", output="d.ply",
                                                   outputs=sdp.Outputs(html="d.html")), "an HTML view"),
                       (lambda: sdp.distance_files("a.npy", "b.npy", output="d.ply", outputs=sdp.Outputs(both=True)),
                        "labelled copy"),
                       (lambda: sdp.compare_files("a.npy", "b.npy", output="c.ply",
                                                  outputs=sdp.Outputs(field_names="pdal")), "field names")):
        with pytest.raises(sdp.InvalidOptionError, match=f"does not write .*{says}"):
            call()


def test_the_documents_name_only_what_exists():
    import importlib
    import re

    root = SRC.parent.parent
    texts = [root / "README.md", root / "pyproject.toml", *sorted((root / "docs").glob("*.md"))]
    missing, absent = [], object()
    for text in texts:
        for name in sorted(set(re.findall(r"\bsdp(?:\.[A-Za-z_]\w*)+", text.read_text()))):
            parts = name.split(".")
            depth = next(i for i in range(len(parts), 0, -1) if ".".join(parts[:i]) in _modules())
            obj = importlib.import_module(".".join(parts[:depth]))
            for part in parts[depth:]:
                obj = getattr(obj, part, absent)
            if obj is absent:
                missing.append(f"{text.name}: {name}")
    assert missing == []
    for package in sorted(p.name for p in SRC.iterdir() if (p / "__init__.pyi").exists() and p.name != "_core"):
        assert f":mod:`sdp.{package}`" in sdp.__doc__, package


def test_the_documents_links_lead_somewhere():
    """Every relative link of README.md and docs/ names a file that exists and, in a Markdown file,
    a heading it has (GitHub's anchors: lower case, punctuation dropped, spaces as dashes)."""
    import re

    root = SRC.parent.parent

    def anchors(path):
        heads = re.findall(r"^#+\s+(.*)$", path.read_text(), flags=re.M)
        return {re.sub(r"[^\w\- ]", "", h.strip().lower()).replace(" ", "-") for h in heads}

    broken = []
    for doc in [root / "README.md", *sorted((root / "docs").glob("*.md"))]:
        for link in re.findall(r"\]\(([^)\s]+)\)", doc.read_text()):
            if link.startswith(("http://", "https://", "mailto:")):
                continue
            path, _, fragment = link.partition("#")
            target = (doc.parent / path).resolve() if path else doc
            if not target.exists() or (fragment and target.suffix == ".md" and fragment not in anchors(target)):
                broken.append(f"{doc.name}: {link}")
    assert broken == []
