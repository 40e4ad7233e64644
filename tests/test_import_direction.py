"""Every import in edygs_ns points down the data flow (issue 17).

The packages form layers; a module may import from its own package, from a lower layer, and from
the neutral basics (``geometry``, ``io``, ``compat``), never from a higher layer or from another
package of its own layer. Imports are read with ``ast`` (module level and inside functions, so a
lazy import counts too), nothing is executed.
"""

from __future__ import annotations

import ast
from pathlib import Path
from typing import Dict, Iterator, List, Optional, Set, Tuple

import pytest

PACKAGE = "edygs_ns"
ROOT = Path(__file__).resolve().parents[1] / PACKAGE

#: Neutral basics every layer may import (shared maths, file I/O, host-framework and CUDA set-up);
#: they import nothing else from edygs_ns (but each other).
NEUTRAL: Tuple[str, ...] = ("geometry", "io", "compat", "cuda_setup")
#: The data flow, lowest first: events -> render/losses -> data/model -> training -> eval ->
#: configs -> scripts. ``sim`` (frames -> events) and ``preprocess`` (raw capture -> processed
#: scene) sit between the events and the packages that read the scenes they write; the method
#: configs assemble data, model and schedule, and the command-line scripts may use them all.
LAYERS: Tuple[Tuple[str, ...], ...] = (
    ("events",),
    ("sim", "render", "losses"),
    ("preprocess",),
    ("data", "model"),
    ("training",),
    ("eval",),
    ("configs",),
    ("scripts",),
)
#: Imports that still point the wrong way, each owned by another item of issue 17. The test fails
#: when one of them is gone, so that the list only shrinks.
PENDING: Dict[Tuple[str, str], str] = {}


def layer_of(package: str) -> Optional[int]:
    """The layer index of a top-level package (None: neutral)."""
    if package in NEUTRAL:
        return None
    for index, members in enumerate(LAYERS):
        if package in members:
            return index
    raise KeyError(f"package {package!r} is in neither LAYERS nor NEUTRAL of {__file__}")


def module_name(path: Path, root: Path = ROOT) -> str:
    parts = list(path.relative_to(root.parent).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def imported_modules(source: str, module: str, is_package: bool = False) -> Iterator[str]:
    """Absolute names of the edygs_ns modules that ``source`` (module ``module``) imports."""
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Import):
            yield from (alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = module.split(".") if is_package else module.split(".")[:-1]
                base = base[: len(base) - node.level + 1]
                target = ".".join(base + ([node.module] if node.module else []))
            else:
                target = node.module or ""
            yield target
            if node.module is None or target == PACKAGE:  # from edygs_ns import geometry
                yield from (f"{target}.{alias.name}" for alias in node.names)


def top_package(module: str) -> Optional[str]:
    parts = module.split(".")
    return parts[1] if parts[0] == PACKAGE and len(parts) > 1 else None


def violations(source: str, module: str, is_package: bool = False) -> List[Tuple[str, str]]:
    """(module, imported module) pairs of ``source`` that import against the data flow."""
    own = top_package(module)
    own_layer = layer_of(own) if own is not None else None
    found = []
    for target in imported_modules(source, module, is_package):
        other = top_package(target)
        if other is None or other == own:
            continue
        other_layer = layer_of(other)
        if other_layer is None:
            continue
        if own is not None and own in NEUTRAL:
            found.append((module, target))
        elif own_layer is not None and other_layer >= own_layer:
            found.append((module, target))
    return found


def package_violations(root: Path = ROOT) -> Set[Tuple[str, str]]:
    found: Set[Tuple[str, str]] = set()
    for path in sorted(root.rglob("*.py")):
        found.update(violations(path.read_text(encoding="utf-8"), module_name(path, root), path.name == "__init__.py"))
    return found


def test_every_package_is_placed() -> None:
    packages = {p.name for p in ROOT.iterdir() if p.is_dir() and (p / "__init__.py").is_file()}
    packages |= {p.stem for p in ROOT.glob("*.py") if p.stem != "__init__"}
    for package in sorted(packages):
        layer_of(package)  # raises KeyError for a package missing from LAYERS and NEUTRAL


def test_imports_point_down_the_data_flow() -> None:
    found = package_violations()
    new = sorted(pair for pair in found if pair not in PENDING)
    assert not new, "imports against the data flow (" + " -> ".join("/".join(layer) for layer in LAYERS) + "):\n" + \
        "\n".join(f"  {module} imports {target}" for module, target in new)


def test_pending_list_only_shrinks() -> None:
    gone = sorted(pair for pair in PENDING if pair not in package_violations())
    assert not gone, "fixed, remove from PENDING in tests/test_import_direction.py: " + ", ".join(map(str, gone))


@pytest.mark.parametrize(
    "module, source, expected",
    [
        ("edygs_ns.events.edi", "from edygs_ns.model.gaussians import GAUSSIAN_ATTRIBUTES\n", ["edygs_ns.model.gaussians"]),
        ("edygs_ns.data.dataparser", "def f():\n    from edygs_ns.eval.trajectory import ate_rmse\n", ["edygs_ns.eval.trajectory"]),
        ("edygs_ns.data.dataparser", "import edygs_ns.model.strategy\n", ["edygs_ns.model.strategy"]),  # sideways
        ("edygs_ns.data.layouts.common", "from ...eval import metrics\n", ["edygs_ns.eval"]),  # relative
        ("edygs_ns.geometry", "from edygs_ns.events.types import EventArray\n", ["edygs_ns.events.types"]),  # neutral
        ("edygs_ns.eval.evaluate", "from edygs_ns.model.gaussians import x\nfrom edygs_ns.io.images import y\n", []),
        ("edygs_ns.scripts.eval", "from edygs_ns import geometry\nfrom edygs_ns.configs import method_configs\n", []),
    ],
)
def test_a_violation_fails(module: str, source: str, expected: List[str]) -> None:
    assert [target for _, target in violations(source, module)] == expected


def test_a_violating_module_in_a_package_tree_is_found(tmp_path: Path) -> None:
    root = tmp_path / PACKAGE
    (root / "events").mkdir(parents=True)
    (root / "events" / "__init__.py").write_text("")
    (root / "events" / "bad.py").write_text("import numpy\n\n\ndef f():\n    from edygs_ns.model import strategy\n")
    (root / "events" / "good.py").write_text("from edygs_ns.geometry import Intrinsics\nfrom . import bad\n")
    assert package_violations(root) == {("edygs_ns.events.bad", "edygs_ns.model")}
