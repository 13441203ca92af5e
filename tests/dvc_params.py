"""The typ/profiles.yaml keys a stage's dvc.yaml entry must depend on."""
from __future__ import annotations

import yaml

from dvc_deps import ROOT


def profile_params(blocks) -> list[str]:
    """``<profile>.<block>`` for every profile of typ/profiles.yaml that sets ``block`` (a profile
    that extends another inherits the others, which the parent's keys already cover)."""
    profiles = yaml.safe_load((ROOT / "typ" / "profiles.yaml").read_text())
    return [f"{p}.{b}" for b in blocks for p, body in profiles.items() if b in body]
