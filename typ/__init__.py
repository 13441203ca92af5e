"""typ — Transfer Your Perspective: turn single-agent LiDAR datasets into collaborative ones."""

__version__ = "0.1.0"
