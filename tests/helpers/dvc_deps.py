"""The project modules a stage's flow imports, transitively: :mod:`flows.dvcyaml`'s, for the tests."""
from __future__ import annotations

from flows.dvcyaml import FOLDERS, ROOT, closure, code_deps, imports_of, module_file  # noqa: F401
