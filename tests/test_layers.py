"""The package layers (docs/architecture.md): a module imports only from its own layer or the layers below it.

Checked on the source's import statements (top-level and inside functions alike), so a function-level import
cannot hide a cycle. An upward import fails the test unless it is listed, with what removing it takes."""

from __future__ import annotations

import ast
from pathlib import Path

SRC = Path(__file__).resolve().parents[1] / "src" / "stgc"

LAYERS = [
    {"errors", "fileio", "config", "run", "distributed", "machine", "official"},  # foundations: no stgc imports but these
    {"data", "render", "metrics"},
    {"model"},
    {"train", "compaction", "codec"},
    {"eval"},
    {"experiment", "demo", "cli", "viewer", "options", "__init__", "__main__"},
]
LEVEL = {name: i for i, names in enumerate(LAYERS) for name in names}

# (importing module, imported package) pairs allowed to point upwards, each with what removing it takes: none.
KNOWN_UPWARD: set[tuple[str, str]] = set()


def _package_of(path: Path) -> str:
    rel = path.relative_to(SRC)
    return rel.parts[0].removesuffix(".py")


def _imported_packages(path: Path) -> set[str]:
    tree = ast.parse(path.read_text(encoding="utf-8"))
    own = _package_of(path)
    # The package a module sits in, as parts below stgc: a relative import of level k climbs k - 1 of them.
    here = list(path.relative_to(SRC).parent.parts)
    found = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom):
            if node.level >= 1:
                base = here[: len(here) - (node.level - 1)] if node.level - 1 <= len(here) else []
                target = base + (node.module.split(".") if node.module else [])
                found.add(target[0] if target else "__init__")
            elif node.module and node.module.split(".")[0] == "stgc":
                parts = node.module.split(".")
                # `from stgc import x`: a submodule, or a name of the root package itself
                found.update([parts[1]] if len(parts) > 1 else
                             [a.name if a.name in LEVEL else "__init__" for a in node.names])
        elif isinstance(node, ast.Import):
            found.update(a.name.split(".")[1] for a in node.names if a.name.startswith("stgc."))
    return {p for p in found if p and p != own}


def test_every_package_is_in_a_layer():
    packages = {_package_of(p) for p in SRC.rglob("*.py")}
    assert packages <= set(LEVEL), sorted(packages - set(LEVEL))


def test_no_module_imports_from_a_higher_layer():
    upward = set()
    for path in SRC.rglob("*.py"):
        own = LEVEL[_package_of(path)]
        for package in _imported_packages(path):
            if LEVEL[package] > own:
                upward.add((str(path.relative_to(SRC)), package))
    assert upward == KNOWN_UPWARD, f"new: {sorted(upward - KNOWN_UPWARD)}, gone: {sorted(KNOWN_UPWARD - upward)}"


# Imported inside functions on purpose: optional extras (gsplat, viser, lpips, tensorboard, pycolmap, ray) that may be
# missing, and matplotlib, whose backend must be chosen before pyplot loads.
OPTIONAL_DEPENDENCIES = {"gsplat", "viser", "lpips", "tensorboard", "torch.utils.tensorboard", "pycolmap", "ray", "matplotlib"}


def test_function_level_imports_are_only_for_optional_dependencies():
    """Everything else is imported at the top of its module, where a cycle fails at import time instead of hiding
    in a function until some verb happens to call it."""
    found = []
    for path in sorted(SRC.rglob("*.py")):
        tree = ast.parse(path.read_text(encoding="utf-8"))
        for function in ast.walk(tree):
            if not isinstance(function, (ast.FunctionDef, ast.AsyncFunctionDef)):
                continue
            for node in ast.walk(function):
                if isinstance(node, ast.Import):
                    names = [a.name for a in node.names]
                elif isinstance(node, ast.ImportFrom):
                    names = ["." * node.level + (node.module or "")]
                else:
                    continue
                for name in names:
                    if not any(name == dep or name.startswith(dep + ".") for dep in OPTIONAL_DEPENDENCIES):
                        found.append(f"{path.relative_to(SRC)}:{node.lineno}: {name}")
    assert found == [], found
