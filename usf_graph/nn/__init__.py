"""Neural-network layers on S2 and R3 built on one distance kernel."""

from ..graph import (
    euclidean_radius,
    euclidean_radius_graph,
    geodesic_radius,
    geodesic_radius_graph,
    knn_graph,
    radius_for_neighbors,
)
from .aggregate import EdgePlan, basis_aggregate
from .colour import grayscale
from .conv import DistanceConv, PointConv, SphericalConv
from .jet import (
    FillHidden,
    GradientPairs,
    LocalJet,
    SurfaceJet,
    UpJet,
    jet_operator,
    tangent_frame,
    up_frame,
)
from .kernel import DistanceKernel
from .norm import MaskedBatchNorm
from .pool import (
    FPSPool,
    GaussianPool,
    GridPool,
    GridUnpool,
    farthest_point_sampling,
    global_max_pool_masked,
    global_mean_pool_area,
)
from .precision import GeometryModule, accumulate_in
from .upright import UprightConv

__all__ = ["FillHidden", "LocalJet", "GradientPairs", "SurfaceJet", "UpJet", "jet_operator", "tangent_frame", "up_frame", "DistanceKernel", "DistanceConv",
           "SphericalConv", "UprightConv", "PointConv", "EdgePlan", "basis_aggregate", "GridPool",
           "GaussianPool", "GridUnpool", "FPSPool", "farthest_point_sampling",
           "MaskedBatchNorm", "global_mean_pool_area", "global_max_pool_masked",
           "euclidean_radius", "geodesic_radius", "geodesic_radius_graph",
           "euclidean_radius_graph", "knn_graph", "radius_for_neighbors", "GeometryModule",
           "accumulate_in", "grayscale"]
