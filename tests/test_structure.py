"""Structure checks: foundations never import stages, entry points never import each other, no package cycles, and
every equation of docs/equations.md names a function that exists."""
from __future__ import annotations

import ast
import importlib
import re
from pathlib import Path

import pytest

SRC = Path(__file__).resolve().parents[1] / "src" / "avatarlab"
DOCS = Path(__file__).resolve().parents[1] / "docs"
#: the foundations: geometry of the head, rendering, the network, the data, the training loop, the measures and the
#: runtime (config, entry point, schema, tracking, provenance, fork server, io, errors) every stage may use
FOUNDATIONS = {"headmodel", "render", "model", "data", "training", "metrics", "runtime"}
#: the pipeline's stages, the workflow's plan and the command line that runs them
STAGES = {"preprocess", "pretrain", "avatar", "speech", "report", "workflow", "cli"}


def module_name(path: Path) -> str:
    rel = path.relative_to(SRC.parent).with_suffix("")
    parts = rel.parts[:-1] if rel.name == "__init__" else rel.parts
    return ".".join(parts)


def runtime_imports(path: Path) -> set[str]:
    """avatarlab modules imported by `path` at run time (imports under `if TYPE_CHECKING:` do not count)."""
    tree = ast.parse(path.read_text())
    skip = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.If) and "TYPE_CHECKING" in ast.unparse(node.test):
            skip.update(id(n) for n in ast.walk(node))
    found = set()
    for node in ast.walk(tree):
        if id(node) in skip:
            continue
        if isinstance(node, ast.ImportFrom) and node.module and node.module.startswith("avatarlab"):
            found.add(node.module)
            found.update(f"{node.module}.{a.name}" for a in node.names)
        elif isinstance(node, ast.Import):
            found.update(a.name for a in node.names if a.name.startswith("avatarlab"))
    modules = {module_name(p) for p in SRC.rglob("*.py")}
    return {m for m in found if m in modules}


def top(module: str) -> str:
    return module.split(".")[1] if "." in module else module


MODULES = {module_name(p): p for p in SRC.rglob("*.py")}


def is_entry_point(path: Path) -> bool:
    return bool(re.search(r"^READS = ", path.read_text(), flags=re.M))


def test_foundations_import_no_stage():
    wrong = [f"{name} imports {imp}" for name, path in MODULES.items() if top(name) in FOUNDATIONS
             for imp in runtime_imports(path) if top(imp) in STAGES]
    assert not wrong, wrong


def test_entry_points_import_no_other_entry_point():
    entries = {name for name, path in MODULES.items() if is_entry_point(path)}
    assert len(entries) >= 15
    wrong = [f"{name} imports {imp}" for name in entries for imp in runtime_imports(MODULES[name])
             if imp in entries and imp != name]
    assert not wrong, wrong


def test_no_import_cycle_between_packages():
    edges = {}
    for name, path in MODULES.items():
        for imp in runtime_imports(path):
            if top(imp) != top(name):
                edges.setdefault(top(name), set()).add(top(imp))

    def reaches(start, goal, seen=()):
        return any(n == goal or (n not in seen and reaches(n, goal, (*seen, n))) for n in edges.get(start, ()))

    cycles = sorted(p for p in edges if reaches(p, p))
    assert not cycles, {p: sorted(edges[p]) for p in cycles}


def test_the_import_checks_can_fail(tmp_path):
    bad = tmp_path / "bad.py"
    bad.write_text("from typing import TYPE_CHECKING\nfrom avatarlab.training.loop import train\n"
                   "if TYPE_CHECKING:\n    from avatarlab.data.splits import subject_split\n")
    assert runtime_imports(bad) == {"avatarlab.training.loop"}  # the TYPE_CHECKING import does not count


def equation_rows() -> list[tuple[str, str]]:
    text = (DOCS / "equations.md").read_text()
    return re.findall(r"^\| *([^|]+?) *\|[^|]*\| *`(avatarlab[\w.]+)`", text, flags=re.M)


def test_equation_index_names_existing_functions():
    rows = equation_rows()
    labels = " ".join(label for label, _ in rows)
    for n in range(1, 12):  # the dissertation's numbered equations (1)-(11)
        assert re.search(rf"\({n}\)", labels), f"eq. ({n}) missing from docs/equations.md"
    for needed in ("seed 000", "seed 001"):
        assert needed in labels, needed
    for label, dotted in rows:
        module, _, attr = dotted.rpartition(".")
        try:
            obj = importlib.import_module(module)
        except ModuleNotFoundError:  # a method: module.Class.method
            module, _, cls = module.rpartition(".")
            obj = getattr(importlib.import_module(module), cls)
        assert callable(getattr(obj, attr, None)), f"{label}: {dotted} does not exist"


@pytest.mark.parametrize("name", ["texture_fit_loss", "phoneme_regularizer"])
def test_named_losses_are_indexed(name):
    assert any(dotted.endswith("." + name) for _, dotted in equation_rows())


def test_no_import_cycle_between_modules():
    """No circle of modules importing each other, imports inside functions included (they hid one in headmodel:
    flame -> sources -> regions -> flame, broken by headmodel/joints.py). A package's __init__ re-exporting its
    modules is not a circle of its own."""
    edges = {name: {imp for imp in runtime_imports(path) if imp in MODULES and imp != name
                    and not name.startswith(imp + ".")}  # a module importing its own package's __init__
             for name, path in MODULES.items()}

    def cycle_from(start):
        stack, seen = [(start, (start,))], set()
        while stack:
            node, path = stack.pop()
            for nxt in edges.get(node, ()):
                if nxt == start:
                    return path
                if nxt not in seen:
                    seen.add(nxt)
                    stack.append((nxt, (*path, nxt)))
        return None

    cycles = {frozenset(c): c for c in (cycle_from(m) for m in MODULES) if c}
    assert not cycles, sorted(" -> ".join(c) for c in cycles.values())


def test_every_entry_points_main_is_a_hydra_step():
    """A module that declares READS is a workflow step: its main() is wrapped by @entry_point(READS) (the workflow
    calls it with no arguments; without the decorator it fails with a TypeError at run time)."""
    steps = {name: path for name, path in MODULES.items() if is_entry_point(path)}
    undecorated = []
    for name, path in steps.items():
        mains = [n for n in ast.parse(path.read_text()).body if isinstance(n, ast.FunctionDef) and n.name == "main"]
        if not mains or not any("entry_point" in ast.unparse(d) for d in mains[0].decorator_list):
            undecorated.append(name)
    assert len(steps) >= 15 and not undecorated, undecorated


def test_every_package_is_a_stage_or_a_foundation_and_the_root_holds_only_the_cli():
    """The folders name the pipeline's stages beside the foundations they share; no loose module at the root but the
    command line."""
    packages = {p.name for p in SRC.iterdir() if p.is_dir() and (p / "__init__.py").exists()}
    assert packages == (FOUNDATIONS | STAGES) - {"cli"}, packages ^ ((FOUNDATIONS | STAGES) - {"cli"})
    assert sorted(p.name for p in SRC.glob("*.py")) == ["__init__.py", "cli.py"]
    entries = {name.split(".")[1] for name, path in MODULES.items() if is_entry_point(path)}
    assert entries <= STAGES - {"workflow", "cli"}, entries  # every workflow step lives in a stage folder
