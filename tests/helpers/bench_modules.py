"""Load a script of bench/ as a module (bench/ is not a package), for the tests of its parts."""
from __future__ import annotations

import importlib.util
import sys
from pathlib import Path
from types import ModuleType
from repo_paths import REPO

ROOT = REPO


def load_bench(name: str) -> ModuleType:
    """``bench/<name>.py``, executed as the module ``bench_<name>``."""
    spec = importlib.util.spec_from_file_location(f"bench_{name}", ROOT / "bench" / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module   # registered before it runs, as an import would (dataclasses look it up)
    spec.loader.exec_module(module)
    return module
