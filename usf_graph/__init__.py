"""usf-graph: the Unified Spherical Frontend for PyTorch Geometric."""

__version__ = "0.1.0"
