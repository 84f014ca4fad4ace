"""The import contract of docs/architecture.md: imports flow one way, from the model up to
the command line.  A module may import from its own layer and the layers below it, never
from a layer above.  Both module-level and function-level (lazy) imports count."""

import ast
from pathlib import Path

import pytest

SRC = Path(__file__).resolve().parent.parent / "src" / "oapcal"

#: Layers, lowest first.  Keys are top-level modules or packages of oapcal.
LAYERS = [
    {"errors", "extras", "records", "progress", "validate"},
    {"model", "_kernels", "_relay_kernel", "eq1_closed_form"},
    {"stats", "normalize", "synthetic", "uncertainty"},
    {"fitting"},
    {"select", "subsampling", "calibration", "error_model"},
    {"imaging", "optics", "families", "selfcal", "entry"},
    {"io"},
    {"batch"},
    {"report"},
    {"demo"},
    {"cli", "__main__", "napari_plugin"},
]
RANK = {name: i for i, layer in enumerate(LAYERS) for name in layer}

#: Imports that break the contract today (none: file writing and figures have left imaging,
#: and stack correction over files lives in ``batch``).  The test fails when a new one
#: appears *and* when a listed one is gone, so this list is always the exact debt.
KNOWN_VIOLATIONS: set[tuple[str, str]] = set()


def _module_name(path: Path) -> str:
    parts = path.relative_to(SRC).with_suffix("").parts
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(parts)


def _imports(path: Path):
    tree = ast.parse(path.read_text(encoding="utf-8"))
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            names = [node.module]
        elif isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        else:
            continue
        for name in names:
            if name.startswith("oapcal."):
                yield name.removeprefix("oapcal.")


def _edges():
    for path in sorted(SRC.rglob("*.py")):
        module = _module_name(path)
        if module == "":  # the package's lazy top level names every layer on purpose
            continue
        for target in _imports(path):
            yield module, target


def _violations():
    found = set()
    for module, target in _edges():
        src_layer, dst_layer = module.split(".")[0], target.split(".")[0]
        assert src_layer in RANK, f"{module}: not in any layer of LAYERS (add it)"
        assert dst_layer in RANK, f"{target}: not in any layer of LAYERS (add it)"
        if RANK[dst_layer] > RANK[src_layer]:
            found.add((module, target))
    return found


def test_every_module_is_in_a_layer():
    tops = {_module_name(p).split(".")[0] for p in SRC.rglob("*.py")} - {""}
    assert tops <= set(RANK), f"modules without a layer: {sorted(tops - set(RANK))}"


def test_imports_flow_one_way():
    new = _violations() - KNOWN_VIOLATIONS
    assert not new, "imports against the layers (docs/architecture.md): " + ", ".join(
        f"{a} -> {b}" for a, b in sorted(new)
    )


def test_the_list_of_known_violations_is_exact():
    gone = KNOWN_VIOLATIONS - _violations()
    assert not gone, f"remove from KNOWN_VIOLATIONS (fixed): {sorted(gone)}"


def test_nothing_imports_the_cli_or_the_report():
    for module, target in _edges():
        top = module.split(".")[0]
        if top not in {"cli", "__main__", "demo", "report", "napari_plugin"}:
            assert not target.startswith(("cli", "report")), f"{module} imports {target}"


def test_nothing_imports_the_napari_plugin():
    """The napari plugin is a top layer beside ``cli``: only napari loads it (its manifest)."""
    for module, target in _edges():
        if module.split(".")[0] != "napari_plugin":
            assert not target.startswith("napari_plugin"), f"{module} imports {target}"
    assert not any(t.startswith("cli") for m, t in _edges() if m.startswith("napari_plugin"))


@pytest.mark.parametrize("module", ["model", "fitting", "select", "subsampling", "calibration", "stats"])
def test_the_core_imports_no_plotting_or_dask(module):
    for path in [SRC / f"{module}.py"]:
        text = path.read_text(encoding="utf-8")
        for heavy in ("matplotlib", "dask", "rich", "click"):
            assert f"import {heavy}" not in text and f"from {heavy}" not in text, (module, heavy)


def test_no_library_module_sets_the_matplotlib_backend():
    """``matplotlib.use`` changes a notebook's backend: figures are built with ``Figure`` and
    ``FigureCanvasAgg`` instead."""
    offenders = [
        str(p.relative_to(SRC))
        for p in SRC.rglob("*.py")
        if "matplotlib.use(" in p.read_text(encoding="utf-8") and not p.is_relative_to(SRC / "cli")
    ]
    assert offenders == [] or set(offenders) <= KNOWN_BACKEND_SETTERS, offenders
    assert KNOWN_BACKEND_SETTERS <= set(offenders), "remove fixed modules from KNOWN_BACKEND_SETTERS"


#: Library modules that still call ``matplotlib.use("Agg")`` (none: figures are built in
#: ``report`` with ``Figure`` + ``FigureCanvasAgg``).
KNOWN_BACKEND_SETTERS: set[str] = set()


def test_tests_mirror_the_source_tree():
    """Each folder of ``tests/`` is named after a module or package of ``src/oapcal`` (the
    tests of that layer); only whole-package tests stay at the top."""
    tests = Path(__file__).resolve().parent
    modules = {p.stem for p in SRC.glob("*.py")} | {p.name for p in SRC.iterdir() if p.is_dir()}
    folders = {p.name for p in tests.iterdir() if p.is_dir() and any(p.glob("test_*.py"))}
    assert folders and folders <= modules, sorted(folders - modules)


#: The modules that read files: ``io.userfile`` opens every user file (text and JSON read
#: there; binary files checked there by ``check_input_file``), then the binary readers
#: decode what it let through; ``io.atomic`` writes.
FILE_READERS = {"io.userfile", "io.images", "io.maps", "io.atomic", "io.digest"}
#: Modules that read files of the package itself, never a user's: the kernels digest the
#: relay tracer's source to name their cache entries (``_kernels._source_tag``).
PACKAGE_READERS = {"_kernels"}
#: Calls that read a file: ``open(...)``; ``x.read_text()``/``x.read_bytes()`` on any path;
#: ``owner.attr(...)`` for the libraries' readers.
_READ_METHODS = {"read_text", "read_bytes"}
_READ_CALLS = {("np", "load"), ("json", "load"), ("cv2", "imread"), ("tifffile", "imread"),
               ("tifffile", "TiffFile"), ("os", "open"), ("os", "fdopen"), ("io", "open")}  # fmt: skip


def _reads_files(path: Path) -> bool:
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if not isinstance(node, ast.Call):
            continue
        func = node.func
        if isinstance(func, ast.Name) and func.id == "open":
            return True
        if isinstance(func, ast.Attribute):
            owner = func.value.id if isinstance(func.value, ast.Name) else None
            # package data (the JSON schemas) is read through importlib.resources: not a user file
            packaged = "resources.files" in ast.unparse(func.value)
            if ((owner, func.attr) in _READ_CALLS or func.attr in _READ_METHODS) and not packaged:
                return True
    return False


def test_only_the_io_file_modules_open_files():
    """One way in for user files (docs/architecture.md, layer 6): every other module reads
    through ``io.userfile``, ``io.images`` or ``io.maps``.  The CLI's stream set-up (``os``
    file descriptors for native libraries' stderr) is not a file read."""
    readers = {_module_name(p) for p in SRC.rglob("*.py") if _reads_files(p)}
    assert readers - {"cli"} - PACKAGE_READERS == FILE_READERS, sorted(readers ^ FILE_READERS)


def test_no_library_module_draws_progress():
    """Progress goes through callbacks (``oapcal.progress``): only the command line and the
    napari plugin draw (Rich bars, napari's own)."""
    drawers = {
        _module_name(p)
        for p in SRC.rglob("*.py")
        if any(t == "rich" or t.startswith("rich.") for t in _all_imports(p))
    }
    assert {m for m in drawers if m.split(".")[0] not in ("cli", "napari_plugin")} == set(), sorted(drawers)


def _all_imports(path: Path):
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            yield node.module
        elif isinstance(node, ast.Import):
            yield from (a.name for a in node.names)
