"""A trained torch module as an MLflow pyfunc model (see :meth:`typ.tracking.StageRun.log_model`).

MLflow's pytorch flavor serves one tensor in, one tensor out; typ's networks take several
named inputs (ε_θ(z_t, t, y^f)) or return output objects (``VQVAEOutput.logits``), a list of
feature maps (the T2I-Adapter) or a dict of heads (the fusion detectors), so they go through
pyfunc: named arrays in, one array (or named arrays) out, the module pickled with the model.
"""
from __future__ import annotations

from importlib import metadata

import mlflow.pyfunc
import numpy as np
import torch


class TorchModule(mlflow.pyfunc.PythonModel):
    """``predict({name: array})`` -> ``module(**tensors)`` (or its ``output`` attribute) as an array."""

    def __init__(self, module: torch.nn.Module, *, output: str | None = None):
        self.module = module
        self.output = output

    def predict(self, context, model_input, params=None) -> np.ndarray | dict[str, np.ndarray]:
        """One array for a tensor output; ``{name: array}`` for a dict of tensors, and
        ``{"level_<i>": array}`` for a list or tuple of them."""
        named = model_input if isinstance(model_input, dict) else {"input": model_input}
        tensors = {k: torch.as_tensor(np.asarray(v)) for k, v in named.items()}
        self.module.eval()
        with torch.no_grad():
            out = self.module(tensors.pop("input"), **tensors) if "input" in tensors else self.module(**tensors)
        if self.output is not None:
            out = getattr(out, self.output)
        if isinstance(out, (list, tuple)):
            out = {f"level_{i}": t for i, t in enumerate(out)}
        if isinstance(out, dict):
            return {k: v.detach().cpu().numpy() for k, v in out.items()}
        return out.detach().cpu().numpy()


def pip_requirements() -> list[str]:
    """The installed versions of what the pickled modules need (skips MLflow's slow inference)."""
    found = []
    for name in ("torch", "numpy", "diffusers", "mlflow"):
        try:
            found.append(f"{name}=={metadata.version(name).split('+')[0]}")
        except metadata.PackageNotFoundError:
            pass
    return found
