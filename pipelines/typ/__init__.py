"""TYP's generator as a diffusers-style pipeline (:class:`TYPPipeline`), with what it is given
(:mod:`pipelines.typ.reference`) and what a view is made of (:mod:`pipelines.typ.compose`, the
compose modes of :data:`typ.registry.COMPOSE_MODES`)."""
from pipelines.typ.pipeline_typ import PointStats, TYPPipeline
from pipelines.typ.reference import Reference, reference_at

__all__ = ["PointStats", "Reference", "TYPPipeline", "reference_at"]
