"""The typ/profiles.yaml keys a stage's dvc.yaml entry must depend on: :mod:`flows.dvcyaml`'s, for the tests."""
from __future__ import annotations

from flows.dvcyaml import profile_params  # noqa: F401
