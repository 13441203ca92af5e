"""Inference pipelines, diffusers-style: trained components and their settings as one object
that ``save_pretrained`` / ``from_pretrained`` move around (:class:`TYPPipeline`: an ego's cloud
in, reference views out, in any compose mode). A pipeline imports models and typ's library
code, never a stage."""
from pipelines.typ import PointStats, Reference, TYPPipeline, reference_at

__all__ = ["PointStats", "Reference", "TYPPipeline", "reference_at"]
