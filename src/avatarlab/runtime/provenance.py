"""What a result was made from: digests of code (by meaning, not by text) and of data files.

The code digest hashes each module's syntax tree without docstrings, so an edit to a comment, a docstring or the
layout changes nothing, while any change to what runs does. The workflow passes it to every rule as a parameter
(Snakemake reruns a step when it changes) and training puts it into its checkpoint fingerprint (a checkpoint is
resumed only by the same code).
"""
from __future__ import annotations

import ast
import hashlib
import json
from functools import lru_cache
from pathlib import Path

SRC = Path(__file__).resolve().parents[2]  # the folder that holds the avatarlab package
#: modules whose edits cannot change a result: experiment tracking, error types, the config schema's checks (they
#: refuse or record, never compute), the dashboard and the CLI. They are not part of any step's code digest.
INFRASTRUCTURE = frozenset({"avatarlab.runtime.tracking", "avatarlab.runtime.errors", "avatarlab.runtime.schema",
                            "avatarlab.runtime.dashboard", "avatarlab.cli"})


def _strip_docstrings(tree: ast.AST) -> ast.AST:
    for node in ast.walk(tree):
        if isinstance(node, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef)):
            body = node.body
            if body and isinstance(body[0], ast.Expr) and isinstance(getattr(body[0], "value", None), ast.Constant) \
                    and isinstance(body[0].value.value, str):
                node.body = body[1:] or [ast.Pass()]
    return tree


def source_digest(path: str | Path) -> str:
    """sha256 of a Python file's syntax tree without docstrings (comments and layout are not in the tree)."""
    return _text_digest(Path(path).read_text(), str(path))


# Parsing is the cost (the Snakefile digests ~25 entry modules sharing most of their imports, at every start of
# Snakemake, in every cluster job too); the caches are keyed by the source text itself, so an edit is never missed.
@lru_cache(maxsize=4096)
def _text_digest(text: str, filename: str) -> str:
    tree = _strip_docstrings(ast.parse(text, filename=filename))
    return hashlib.sha256(ast.dump(tree, include_attributes=False).encode()).hexdigest()


@lru_cache(maxsize=4096)
def _imports(text: str, package: str) -> tuple[str, ...]:
    """The avatarlab modules one source text imports (relative imports resolved against `package`)."""
    found = []
    for node in ast.walk(ast.parse(text)):
        if isinstance(node, ast.Import):
            found += [a.name for a in node.names if a.name.startswith("avatarlab")]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                pkg = package.split(".")
                base = ".".join(pkg[: len(pkg) - node.level + 1] + ([base] if base else []))
            if base.startswith("avatarlab"):
                found.append(base)
                found += [f"{base}.{a.name}" for a in node.names]
    return tuple(found)


def module_path(name: str, src: Path = SRC) -> Path:
    """a.b.c -> src/a/b/c.py, or src/a/b/c/__init__.py for a package."""
    parts = name.split(".")
    source = src.joinpath(*parts[:-1], parts[-1] + ".py")
    return source if source.is_file() else src.joinpath(*parts, "__init__.py")


def imported_modules(*entry_modules: str, src: Path = SRC) -> list[str]:
    """The avatarlab modules an entry module runs: itself and everything it imports from avatarlab, transitively
    (found by parsing imports, not by importing)."""
    seen: set[str] = set()
    todo = list(entry_modules)
    while todo:
        name = todo.pop()
        path = module_path(name, src)
        if name in seen or not path.is_file():
            continue
        seen.add(name)
        parts = name.split(".")
        package = name if path.name == "__init__.py" else ".".join(parts[:-1])
        todo += _imports(path.read_text(), package)
        while len(parts) > 1:  # importing a.b.c runs a/__init__ and a/b/__init__
            parts = parts[:-1]
            todo.append(".".join(parts))
    return sorted(seen)


def code_digest(*entry_modules: str, src: Path = SRC) -> str:
    """One digest of the code an entry module runs (see `imported_modules`), infrastructure modules left out."""
    h = hashlib.sha256()
    for name in imported_modules(*entry_modules, src=src):
        if name in INFRASTRUCTURE:
            continue
        h.update(f"{name}:{source_digest(module_path(name, src))}\n".encode())
    return h.hexdigest()[:16]


def file_digest(path: str | Path, chunk: int = 1 << 20) -> str:
    """sha256 of a file's bytes (a folder: of its files' names and digests)."""
    path = Path(path)
    h = hashlib.sha256()
    if path.is_dir():
        for child in sorted(p for p in path.rglob("*") if p.is_file()):
            h.update(f"{child.relative_to(path)}:{file_digest(child)}\n".encode())
        return h.hexdigest()[:16]
    with open(path, "rb") as f:
        while block := f.read(chunk):
            h.update(block)
    return h.hexdigest()[:16]


def fingerprint(settings: dict, code: str, data: dict[str, str | Path | None]) -> str:
    """The identity of one piece of work: its resolved settings, its code digest and its data files' digests."""
    files = {name: file_digest(p) if p and Path(p).exists() else None for name, p in sorted(data.items())}
    payload = json.dumps({"settings": settings, "code": code, "data": files}, sort_keys=True, default=str)
    return hashlib.sha256(payload.encode()).hexdigest()[:24]
