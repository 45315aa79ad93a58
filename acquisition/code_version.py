"""Code versions: the hash of the code some modules run (theirs and every project module they import), each as
its syntax tree without docstrings and comments, so only a change of behaviour re-versions what it made.

The pipeline's cache keys stages by it; the twin records it in every simulated session, so a session made by
other code is never taken for one this code would make.

Normalising a module (parse, strip, dump) costs ~6 ms; the twin's ~100 modules ~0.6 s a process, paid by
every command and simulation worker that versions what it makes. Each module's normal form is therefore
kept on disk under the hash of its source bytes (``NORMAL_FORMS``, the user's cache folder): a file read
again is a file read, and an edited one is a new key. A cache that cannot be written is not used.
"""

from __future__ import annotations

import ast
import hashlib
import json
import os
import sys
from functools import cache
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("acquisition", "twin", "pipeline", "models", "analysis")  # whose code a result can depend on
_FORM = 1  # the normal form's own version: a change to how it is made makes every kept one another key
NORMAL_FORMS = (
    Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "vslab" / "code-normal-forms"
)


def _without_docstrings(tree: ast.AST) -> ast.AST:
    for node in ast.walk(tree):
        body = getattr(node, "body", None)
        if (
            isinstance(node, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef))
            and body
            and isinstance(body[0], ast.Expr)
            and isinstance(body[0].value, ast.Constant)
            and isinstance(body[0].value.value, str)
        ):
            node.body = body[1:]
    return tree


def _module_file(name: str, root: Path) -> Path | None:
    base = root.joinpath(*name.split("."))
    for path in (base.with_suffix(".py"), base / "__init__.py"):
        if path.is_file():
            return path
    return None


def _imports(tree: ast.AST, name: str, is_package: bool) -> set[str]:
    """The project modules a module's code imports, wherever the import stands (a function's lazy import
    too): ``from a import b`` counts ``a`` and, where it is a module, ``a.b``."""
    found = set()
    package = name if is_package else name.rpartition(".")[0]
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                parts = package.split(".")
                base = ".".join(parts[: len(parts) - node.level + 1])
                module = f"{base}.{node.module}" if node.module else base
            else:
                module = node.module or ""
            found.add(module)
            found.update(f"{module}.{alias.name}" for alias in node.names)
    return {m for m in found if m.split(".")[0] in PACKAGES}


@cache
def _normalised(name: str, root: Path) -> tuple[str, frozenset[str]] | None:
    """The hash of a module's code as its syntax tree without docstrings (comments never reach the tree) and
    the project modules it imports; None where ``name`` is not a module of ours (an imported function's
    name)."""
    path = _module_file(name, root)
    if path is None:
        return None
    source = path.read_bytes()
    key = hashlib.sha256(f"{_FORM} {sys.version_info[:2]} {name} {path.name}\n".encode() + source).hexdigest()
    kept = NORMAL_FORMS / f"{key}.json"
    try:
        tree_hash, imports = json.loads(kept.read_text())
        return tree_hash, frozenset(imports)
    except (OSError, ValueError, TypeError):  # not kept yet (or a torn file): made, and kept
        pass
    tree = _without_docstrings(ast.parse(source, filename=str(path)))
    dumped = ast.dump(tree, annotate_fields=False, include_attributes=False)
    made = (
        hashlib.sha256(dumped.encode()).hexdigest(),
        sorted(_imports(tree, name, path.name == "__init__.py")),
    )
    try:
        NORMAL_FORMS.mkdir(parents=True, exist_ok=True)
        partial = kept.with_name(f"{key}.{os.getpid()}.tmp")
        partial.write_text(json.dumps(made))
        os.replace(partial, kept)  # whole or not at all: another process may be keeping the same one
    except OSError:
        pass
    return made[0], frozenset(made[1])


def code_version(*modules: str, root: Path | None = None) -> str:
    """Hash of the code that ``modules`` run: theirs and every project module they import, transitively (and
    the packages holding them). ``root``: the checkout whose code is read (this one by default)."""
    return _tree_version(modules, Path(ROOT if root is None else root))


@cache
def _tree_version(modules: tuple[str, ...], root: Path) -> str:
    """``code_version`` of ``modules`` under ``root``, worked out once per process."""
    pending = list(modules)
    seen: dict[str, str] = {}
    while pending:
        name = pending.pop()
        if name in seen:
            continue
        module = _normalised(name, root)
        if module is None:
            seen[name] = ""
            continue
        seen[name], imports = module
        parents = {name.rsplit(".", k)[0] for k in range(1, name.count(".") + 1)}  # their __init__ runs first
        pending.extend((imports | parents) - seen.keys())
    h = hashlib.sha256()
    for name in sorted(seen):
        if seen[name]:
            h.update(f"{name}\n{seen[name]}\n".encode())
    return h.hexdigest()[:16]
