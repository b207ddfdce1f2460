"""srfpipe: Semantic Radiance Field simulators from posed RGB captures."""

__version__ = "0.1.0"
