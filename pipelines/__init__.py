"""Inference pipelines, diffusers-style: trained components and their settings as one object
that ``save_pretrained`` / ``from_pretrained`` move around (:class:`TYPPipeline`: an ego's cloud
in, a reference view out). A pipeline imports models and typ's library code, never a stage."""
from pipelines.pipeline_typ import PointStats, TYPPipeline

__all__ = ["PointStats", "TYPPipeline"]
