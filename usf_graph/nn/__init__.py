"""Neural-network layers on S2 and R3 built on one distance kernel."""

from .graph import euclidean_radius_graph, geodesic_radius_graph, knn_graph, radius_for_neighbors

__all__ = ["geodesic_radius_graph", "euclidean_radius_graph", "knn_graph", "radius_for_neighbors"]
