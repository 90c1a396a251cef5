"""Operations on spherical boxes (see :mod:`usf_graph.ops.boxes`)."""

from .boxes import (
                    box_axes,
                    box_corners,
                    box_edges,
                    box_planes,
                    boxes_from_axes,
                    canonical_boxes,
                    fit_box,
                    from_pandora,
                    points_in_boxes,
                    rotate_boxes,
                    share_in_view,
                    to_pandora,
)
from .iou import box_area, box_iou, nms_keep, pairwise_box_iou, spherical_nms

__all__ = ["box_area", "box_iou", "nms_keep", "pairwise_box_iou", "spherical_nms", "box_planes", "box_axes", "box_corners", "box_edges", "boxes_from_axes", "canonical_boxes", "fit_box", "from_pandora",
           "points_in_boxes", "rotate_boxes", "share_in_view", "to_pandora"]
