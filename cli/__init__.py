"""The ``typ`` command line: the layer above the flows (CLI -> flows -> tasks -> models, typ)."""
