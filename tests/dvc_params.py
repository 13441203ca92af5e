"""The typ/profiles.yaml keys a stage's dvc.yaml entry must depend on: :mod:`typ.dvcyaml`'s, for the tests."""
from __future__ import annotations

from typ.dvcyaml import profile_params  # noqa: F401
