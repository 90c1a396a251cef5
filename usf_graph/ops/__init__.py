"""Operations on spherical boxes (see :mod:`usf_graph.ops.boxes`)."""

from .boxes import (
                    box_axes,
                    box_corners,
                    box_edges,
                    boxes_from_axes,
                    fit_box,
                    from_pandora,
                    points_in_boxes,
                    rotate_boxes,
                    to_pandora,
)

__all__ = ["box_axes", "box_corners", "box_edges", "boxes_from_axes", "fit_box", "from_pandora",
           "points_in_boxes", "rotate_boxes", "to_pandora"]
