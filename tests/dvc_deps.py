"""The project modules a stage's flow imports, transitively (imports inside functions too)."""
from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("typ", "tasks", "models", "flows")


def module_file(name: str) -> Path | None:
    """``a.b.c`` -> its file under the project, or None when it is not a project module."""
    if name.split(".")[0] not in PACKAGES:
        return None
    path = ROOT.joinpath(*name.split("."))
    if path.with_suffix(".py").is_file():
        return path.with_suffix(".py")
    if (path / "__init__.py").is_file():
        return path / "__init__.py"
    return None


def imports_of(path: Path) -> set[str]:
    """Dotted names of every module ``path`` imports (``from a import b`` gives ``a`` and ``a.b``)."""
    tree = ast.parse(path.read_text())
    package = ".".join(path.relative_to(ROOT).with_suffix("").parts[:-1])
    names: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                parts = package.split(".")[: len(package.split(".")) - node.level + 1]
                base = ".".join([*parts, base] if base else parts)
            names.add(base)
            names.update(f"{base}.{a.name}" for a in node.names)
    return names


def closure(start: str) -> set[Path]:
    """Files of every project module reachable from module ``start`` (it included)."""
    seen: set[Path] = set()
    todo = [start]
    while todo:
        name = todo.pop()
        parts = name.split(".")
        for k in range(1, len(parts) + 1):   # a.b.c also imports a and a.b
            f = module_file(".".join(parts[:k]))
            if f is not None and f not in seen:
                seen.add(f)
                todo.extend(imports_of(f))
    return seen


#: sub-packages a stage uses whole: declared as one folder dep
FOLDERS = ("typ/sim", "typ/formats", "typ/sensors")


def code_deps(stage: str) -> list[str]:
    """The code deps stage ``stage``'s dvc.yaml entry must list: its flow's import closure, with
    :data:`FOLDERS` as folders."""
    out = set()
    for path in closure(f"flows.{stage}"):
        rel = str(path.relative_to(ROOT))
        folder = next((f for f in FOLDERS if rel.startswith(f + "/")), None)
        out.add(folder or rel)
    return sorted(out)
