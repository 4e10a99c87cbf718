"""The layers of src/pipe point one way: data -> model | synthetic | importing -> training | evaluation ->
pipeline -> entry points.

Every import in every module of the package (module level or inside a function) is parsed; a module may
import from its own package and from lower layers only. Siblings on one layer (training and evaluation,
model, synthetic and importing) never import each other.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest
from conftest import ROOT

PACKAGE = ROOT / "src" / "pipe"
LAYERS = {                      # top-level module or subpackage of pipe -> layer
    "__init__": 0, "errors": 0, "files": 0, "machine": 0,
    "data": 1, "kernels": 1, "registry": 1, "store": 1, "threads": 1,
    "model": 2, "synthetic": 2, "importing": 2, "settings": 2,
    "training": 3, "evaluation": 3, "tracking": 3, "dataset_check": 3,
    "pipeline": 4, "predict": 4, "params": 4, "sweeps": 4,
    "cli": 5, "app": 6,
}


def unit(module: str) -> str:
    """The layered unit of a dotted module name inside pipe: `pipe.data.batches` -> `data`."""
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else "__init__"


def is_submodule(root: Path, name: str) -> bool:
    return (root / name).is_dir() or (root / f"{name}.py").is_file()


def imports(path: Path, root: Path) -> list[tuple[int, str]]:
    """(line, module) of every pipe import in a file, with relative imports resolved; `from pipe import x`
    counts as an import of the submodule x, or of the package's own `__init__` when x is a name in it."""
    package = ".".join(path.relative_to(root.parent).with_suffix("").parts)
    if path.name != "__init__.py":
        package = package.rsplit(".", 1)[0]
    found = []
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            found += [(node.lineno, alias.name) for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                parent = package.split(".")[: len(package.split(".")) - node.level + 1]
                base = ".".join(parent + ([base] if base else []))
            names = [f"pipe.{a.name}" if base == "pipe" and is_submodule(root, a.name) else base
                     for a in node.names]
            found += [(node.lineno, name) for name in names]
    return [(line, name) for line, name in found if name == "pipe" or name.startswith("pipe.")]


def violations(root: Path = PACKAGE) -> list[str]:
    problems = []
    for path in sorted(root.rglob("*.py")):
        source = unit(".".join(path.relative_to(root.parent).with_suffix("").parts))
        if source not in LAYERS:
            problems.append(f"{path.relative_to(root)}: not in the layer map; give `{source}` a layer")
            continue
        for line, target in imports(path, root):
            dest = unit(target)
            if dest == source or dest == "__init__":
                continue
            if dest not in LAYERS:
                problems.append(f"{path.relative_to(root)}:{line} imports unknown {target}")
            elif LAYERS[dest] >= LAYERS[source]:
                kind = "sibling" if LAYERS[dest] == LAYERS[source] else "upward"
                problems.append(f"{path.relative_to(root)}:{line}: {kind} import of {target} ({source} is layer "
                                f"{LAYERS[source]}, {dest} is layer {LAYERS[dest]})")
    return problems


def test_imports_only_point_down():
    assert violations() == []


@pytest.mark.parametrize("module, line, expected", [
    ("data/leak.py", "from pipe.evaluation.metrics import rms", "upward import of pipe.evaluation.metrics"),
    ("evaluation/leak.py", "from pipe.training.stages import HeadStage", "sibling import of pipe.training.stages"),
    ("model/leak.py", "def f():\n    import pipe.synthetic.generate", "sibling import of pipe.synthetic.generate"),
    ("data/leak.py", "from ..pipeline import run_domain", "upward import of pipe.pipeline"),
    ("data/ok.py", "from pipe.data.spec import load_spec\nfrom pipe.errors import PipeError", None),
])
def test_the_check_catches_upward_and_sibling_imports(tmp_path, module, line, expected):
    """The rule on a throwaway package tree: each kind of violation is found, and allowed imports pass."""
    root = tmp_path / "pipe"
    (root / Path(module).parent).mkdir(parents=True)
    (root / "__init__.py").write_text("")
    (root / Path(module).parent / "__init__.py").write_text("")
    (root / module).write_text(line + "\n")
    found = violations(root)
    assert (found == []) if expected is None else (len(found) == 1 and expected in found[0])
