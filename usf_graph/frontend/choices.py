"""The frontend's named choices, in a module that imports nothing, so that the command
line's help lists them without loading torch."""

#: Ways to interpolate an image at the grid's points (:func:`~usf_graph.frontend.interpolation.check_method`).
METHODS = ("bilinear", "nearest", "area", "rbf")
#: How a rig's cameras share the directions several see (:func:`~usf_graph.frontend.rig.blend_weights`).
BLENDS = ("best", "feather")
