"""The detectors: exact equivariance of the spherical box head, targets that decode back to
their boxes (spherical and planar), losses that train, bad inputs."""

import math

import numpy as np
import pytest
import torch

from usf_graph import grids
from usf_graph.frontend import grid_graph
from usf_graph.geometry import geodesic_distance, rotation_from_axis_angle
from usf_graph.models import PlanarDetector, SphericalDetector
from usf_graph.models.centernet import (
    box_centres,
    expmap,
    fields_on_cpu,
    focal_loss,
    heatmap_targets,
    logmap,
    nearest_points,
    neighbour_table,
    peaks,
)
from usf_graph.nn import SurfaceJet, geodesic_radius_graph
from usf_graph.ops import box_corners, box_iou, rotate_boxes
from usf_graph.testing import smooth_signal, symmetry_permutation

SMALL = dict(num_classes=3, input_level=3, head_level=2, min_level=1, channels=(4, 6, 8),
             pairs=2, gradient_fields=2)
# seam, pole, roll +-90, tall and wide boxes (radians)
BOXES = torch.tensor(np.radians([[179.0, 10, 30, 20, 0], [-40, 84, 25, 40, 0],
                                 [60, -20, 12, 50, 90], [-120, 5, 60, 15, -90],
                                 [10, 30, 40, 40, 30], [100, -70, 20, 10, 0]]))


def test_logmap_inverts_expmap_and_nearest_points_brute_force():
    g = torch.Generator().manual_seed(0)
    p = torch.nn.functional.normalize(torch.randn(200, 3, generator=g, dtype=torch.float64), dim=-1)
    q = torch.nn.functional.normalize(torch.randn(200, 3, generator=g, dtype=torch.float64), dim=-1)
    v = logmap(p, q)
    # tangent at p, as long as the arc, and exp brings it back to q
    assert (v * p).sum(-1).abs().max() < 1e-12
    torch.testing.assert_close(v.norm(dim=-1), geodesic_distance(p, q), rtol=0, atol=1e-12)
    torch.testing.assert_close(expmap(p, v), q, rtol=0, atol=1e-12)
    assert logmap(p, p).abs().max() < 1e-15  # no way to go
    # a quarter turn about z takes x to y: the tangent at x is pi/2 along y
    x, y = torch.eye(3, dtype=torch.float64)[:2]
    torch.testing.assert_close(logmap(x, y), y * np.pi / 2, rtol=0, atol=1e-15)
    pts = grids.icosahedral(2).pos.double()
    near = nearest_points(BOXES, pts)
    brute = geodesic_distance(box_centres(BOXES)[:, None], pts[None]).argmin(1)
    assert torch.equal(near, brute)
    assert torch.equal(nearest_points(BOXES.float(), pts), near)


def _icosahedral_symmetry(level):
    pos = grids.icosahedral(level).pos
    axis = pos[0] / pos[0].norm()  # an icosahedron vertex: a 5-fold axis
    R = rotation_from_axis_angle(axis, torch.tensor(2 * np.pi / 5, dtype=torch.float64))
    return R, symmetry_permutation(pos, R)


def _same_boxes(a, b, tol):
    """Largest corner distance between box sets matched in order (a box's corners can be
    listed from another start after a roll wraps, so match each corner to the nearest)."""
    ca, cb = box_corners(torch.as_tensor(a)), box_corners(torch.as_tensor(b))
    d = torch.cdist(ca, cb).amin(-1).amax()
    return float(d) <= tol


def test_peaks_are_the_local_maxima_above_the_threshold():
    g = grids.icosahedral(2)
    edges, _ = grid_graph(g, 1.5 * g.spacing)
    M = len(g.pos)
    prob = torch.rand(M, 3, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    near = {i: set() for i in range(M)}  # the reference reads the edge list itself
    for j, i in edges.T.tolist():
        near[i].add(j)
    want = sorted(((float(prob[i, c]), i, c) for i in range(M) for c in range(3)
                   if prob[i, c] > 0.3 and all(prob[i, c] >= prob[j, c] for j in near[i])), reverse=True)
    assert 10 < len(want) < M  # some points are peaks, most are not
    table = neighbour_table(edges, M)
    for k in (len(want) + 20, 7):
        pt, cls, score = peaks(prob, table, k, 0.3)
        assert len(pt) == k  # fixed in shape; the peaks are the rows above the threshold
        got = [(float(s), int(p), int(c)) for p, c, s in zip(pt, cls, score) if s > 0.3]
        assert got == want[:k]
        assert (score[len(got):] == 0).all()


def test_surface_jet_gives_tangent_gradients_of_linear_functions():
    g = grids.icosahedral(4)  # the fit's truncation error (~|u|^2/6 relative) is ~0.6% here
    ei, ew = geodesic_radius_graph(g.pos, 3.5 * g.spacing)
    jet = SurfaceJet(g.pos, ei, ew, g.spacing).double()
    a = torch.tensor([0.3, -0.8, 0.5], dtype=torch.float64)
    d = jet((g.pos @ a)[None, :, None])[0, :, 0]  # [N, 5]
    grad = d[:, :1] * jet.frame[:, 0] + d[:, 1:2] * jet.frame[:, 1]
    want = a - (g.pos @ a)[:, None] * g.pos  # the surface gradient of p . a
    assert (grad - want).abs().max() < 1e-2 * a.norm()
    # Hessian of p . a on the sphere: -(p . a) I on the tangent plane
    assert (d[:, 2] + g.pos @ a).abs().max() < 2e-2 and d[:, 3].abs().max() < 2e-2


@pytest.mark.parametrize("gravity, upright, upright_convs", [
    (False, False, None), (True, False, None), (True, True, None), (True, True, 2)])
def test_spherical_detector_is_exactly_equivariant_under_grid_symmetries(gravity, upright,
                                                                         upright_convs):
    torch.manual_seed(4)  # a seed whose random boxes differ in size and roll (checked below)
    m = SphericalDetector(**SMALL, gravity=gravity, upright=upright,
                          upright_convs=upright_convs).double().eval()
    with torch.no_grad():  # a rough head: many peaks of many shapes
        m.head.weight.mul_(30)
        if gravity:  # peaked up scores, so that the estimate is well defined
            m.gravity.head.score.weight.mul_(50)
    R, sigma = _icosahedral_symmetry(3)
    pos = grids.icosahedral(3).pos
    x = torch.as_tensor(smooth_signal(pos.numpy()))[None] + torch.randn(1, len(pos), 3, dtype=torch.float64)
    xr = torch.empty_like(x)
    xr[:, sigma] = x
    with torch.no_grad():
        out, outr = m(x), m(xr)
    # every field at every head point: scalars permute, the offset rotates
    _, sh = _icosahedral_symmetry(SMALL["head_level"])
    for f in ("heat", "s"):
        assert (outr[f][:, sh] - out[f]).abs().max() < 1e-9
    assert (outr["offset"][:, sh] - out["offset"] @ R.T).abs().max() < 1e-12
    assert out["offset"].norm(dim=-1).max() > 1e-5  # not zero, so the check above bites
    if gravity:  # the up estimate rotates with the input
        assert (outr["gravity"]["up"] - out["gravity"]["up"] @ R.T).abs().max() < 1e-9
    # spin-2 and spin-4 fields turn by 2 and 4 times the frame angle: compare frame-free
    for f in ("dev", "quad"):
        assert (outr[f][:, sh].norm(dim=-1) - out[f].norm(dim=-1)).abs().max() < 1e-12
    kw = dict(k=100, threshold=0.0, nms=None)
    d, dr = m.decode(out, **kw)[0], m.decode(outr, **kw)[0]
    assert len(d["boxes"]) >= 3 and np.unique(d["scores"]).size == len(d["scores"])
    np.testing.assert_allclose(dr["scores"], d["scores"], rtol=0, atol=1e-12)
    np.testing.assert_array_equal(dr["classes"], d["classes"])
    assert _same_boxes(dr["boxes"], rotate_boxes(d["boxes"], R.numpy()), 1e-6)
    # the boxes are not trivial: different shapes and orientations
    assert np.ptp(d["boxes"][:, 2]) > 1e-3 and np.ptp(d["boxes"][:, 4]) > 0.1


def _perfect_fields(model, boxes, classes):
    """The fields a perfect spherical detector would output: heat 1 at each box's centre
    point, and at that point the targets the loss trains towards."""
    t = model.targets(boxes, classes, torch.zeros(len(boxes), dtype=torch.long), 1)
    M = len(model.head_pos)
    heat = torch.full((1, M, model.num_classes), -20.0, dtype=torch.float64)
    heat[0, t["nearest"], classes] = 20.0
    out = {"heat": heat, "s": torch.zeros(1, M, dtype=torch.float64),
           "offset": torch.zeros(1, M, 3, dtype=torch.float64),
           "dev": torch.zeros(1, M, 2, dtype=torch.float64),
           "quad": torch.zeros(1, M, 2, dtype=torch.float64), "mask": None}
    for k, p in enumerate(t["nearest"].tolist()):
        r = torch.nonzero((t["point"] == p) & (t["box"] == k)).flatten()[0]
        for f in ("s", "offset", "dev", "quad"):
            out[f][0, p] = t[f][r]
    return out


def test_spherical_targets_decode_back_to_their_boxes():
    m = SphericalDetector(**SMALL).double()
    classes = torch.tensor([0, 1, 2, 0, 1, 2])
    det = m.decode(_perfect_fields(m, BOXES, classes), threshold=0.5)[0]
    assert len(det["boxes"]) == len(BOXES)
    order = np.argsort(det["boxes"][:, 0])
    ref = np.argsort(BOXES[:, 0].numpy())
    iou = box_iou(torch.as_tensor(det["boxes"][order]), BOXES[ref], dtype=torch.float64)
    assert iou.min() > 0.97  # axes moved from the grid point to the centre by projection
    np.testing.assert_array_equal(det["classes"][order], classes[ref].numpy())


def test_offset_potential_gives_the_log_map():
    """An offset field -d^2 / 2h^2 around a centre decodes to that centre from every point
    near it (the jet's quadratic fit of the potential)."""
    m = SphericalDetector(**SMALL).double()
    P, h, C = m.head_pos, m.head_spacing, m.num_classes
    c = torch.nn.functional.normalize(torch.tensor([[0.3, 0.5, 0.7]], dtype=torch.float64), dim=-1)
    d = torch.atan2(torch.linalg.cross(P, c.expand_as(P)).norm(dim=-1), P @ c[0])
    f = torch.zeros(1, len(P), m.head.out_features, dtype=torch.float64)
    f[0, :, C + 1] = -d ** 2 / (2 * h * h)
    near = torch.nonzero(d < 1.5 * h).flatten()
    err = (m._fields(f, None)["offset"][0, near] - logmap(P[near], c)).norm(dim=-1)
    assert len(near) >= 4 and err.max() < 0.02 * h


def _planar_box_fields(m, boxes, image, point, box, num_images=1):
    """Box fields ``[num_images, M, 5]`` that, at output pixel ``point[i]`` of image
    ``image[box[i]]``, decode to ``boxes[box[i]]`` (zero elsewhere)."""
    W = m.out_camera.width
    uv = m._pixels(box_centres(boxes))[box]
    off = torch.stack([uv[:, 0] - point % W, uv[:, 1] - point // W], -1)
    off[:, 0] = torch.remainder(off[:, 0] + W / 2, W) - W / 2
    f = torch.zeros(num_images, len(m.points), 5, dtype=torch.float64)
    f[image[box], point] = torch.cat([off, boxes[box, 2:4].log(), boxes[box, 4:]], -1)
    return f


def _planar_perfect_fields(m, boxes, classes):
    """The planar detector's fields that decode to ``boxes`` (as a perfect one's)."""
    image = torch.zeros(len(boxes), dtype=torch.long)
    heat_t, near, _ = heatmap_targets(m.points, boxes, classes, image, 1, m.num_classes, m.spacing)
    heat = torch.full((1, len(m.points), m.num_classes), -20.0, dtype=torch.float64)
    heat[0, near, classes] = 20.0
    box = _planar_box_fields(m, boxes, image, near, torch.arange(len(boxes)))
    return {"heat": heat, "box": box, "mask": None}


def test_planar_targets_decode_back_to_their_boxes():
    m = PlanarDetector(num_classes=3, height=64, width=128, channels=(4, 8)).double()
    classes = torch.tensor([0, 1, 2, 0, 1, 2])
    boxes = BOXES.clone()
    boxes[:, 4] = torch.tensor([0.0, 0.0, 0.3, -0.4, 0.5, 0.0])  # rolls within [-pi/2, pi/2)
    det = m.decode(_planar_perfect_fields(m, boxes, classes), threshold=0.5)[0]
    order, ref = np.argsort(det["boxes"][:, 0]), np.argsort(boxes[:, 0].numpy())
    np.testing.assert_allclose(det["boxes"][order], boxes[ref].numpy(), atol=1e-9)


def test_planar_peaks_are_8_neighbour_maxima_wrapping_in_longitude():
    m = PlanarDetector(num_classes=1, height=8, width=12, channels=(4, 8))
    H, W = 4, 6  # its output map
    rows = [set(row.tolist()) for row in m.ring]
    for r in range(H):
        for c in range(W):
            want = {rr * W + (c + dc) % W for rr in (r - 1, r, r + 1) if 0 <= rr < H
                    for dc in (-1, 0, 1)}
            assert rows[r * W + c] == want, (r, c)
    # across the seam: the first column's value loses to a higher one in the last column
    prob = torch.zeros(H * W, 1)
    prob[1 * W + 0], prob[2 * W + W - 1], prob[3 * W + 2] = 0.8, 0.9, 0.7
    point, _, score = peaks(prob, m.ring, 3, 0.5)
    assert point[score > 0].tolist() == [2 * W + W - 1, 3 * W + 2]


def test_planar_loss_trains_the_fields_that_decode_to_the_boxes():
    """At every regression sample the loss's box target is what decodes to that sample's box:
    fields built so (and checked by decoding them) cost nothing, a pixel off costs."""
    m = PlanarDetector(num_classes=3, height=64, width=128, channels=(4, 8)).double()
    boxes = BOXES.clone()
    boxes[:, 4] = torch.tensor([0.0, 0.0, 0.3, -0.4, 0.5, 0.0])  # rolls within [-pi/2, pi/2)
    classes, image = torch.tensor([0, 1, 2, 0, 1, 2]), torch.tensor([0, 0, 0, 1, 1, 1])
    for k in (6, 1):  # one box alone too
        boxes, classes, image = boxes[:k], classes[:k], image[:k]
        _, _, (point, box, _) = heatmap_targets(m.points, boxes, classes, image, 2, 3, m.spacing)
        assert len(point) > 2 * len(boxes)  # dense regression: several samples per box
        out = {"heat": torch.zeros(2, len(m.points), 3, dtype=torch.float64),
               "box": _planar_box_fields(m, boxes, image, point, box, 2), "mask": None}
        for b in (0, 1):
            mine = image[box] == b
            np.testing.assert_allclose(m.boxes_at(out, b, point[mine]), boxes[box[mine]], atol=1e-9)
        assert m.loss(out, boxes, classes, image)[1]["box"] < 1e-9
        out["box"][..., 1] += 1.0
        loss, stats = m.loss(out, boxes, classes, image)
        assert stats["box"] == pytest.approx(1.0) and loss.item() == pytest.approx(stats["heat"] + 1.0)


def test_planar_loss_without_boxes_and_with_a_mask():
    m = PlanarDetector(num_classes=3, height=32, width=64, channels=(4, 8)).double()
    mask = torch.zeros(32, 64, dtype=torch.bool)
    mask[:, :20] = True
    mask[30, 40] = True  # one pixel: its output pixel (15, 20) is seen in part
    out = m(torch.rand(2, 3, 32, 64, dtype=torch.float64), mask)
    assert torch.equal(out["seen"], mask.flatten())
    seen = torch.zeros(16, 32, dtype=torch.bool)
    seen[:, :10], seen[15, 20] = True, True
    assert torch.equal(out["mask"], seen.flatten())
    none = (torch.zeros(0, 5, dtype=torch.float64), torch.zeros(0, dtype=torch.long),
            torch.zeros(0, dtype=torch.long))
    loss, stats = m.loss(out, *none)
    assert stats["box"] == 0 and loss.item() == pytest.approx(stats["heat"])
    loss.backward()  # the box fields are in the graph (DDP needs every parameter used)
    assert m.body.head[-1].weight.grad[3:].abs().sum() == 0
    # the heatmaps where the camera does not see are not scored
    hidden = {**out, "heat": out["heat"].detach().masked_fill(~out["mask"][None, :, None], 9.0)}
    torch.testing.assert_close(m.loss(hidden, *none)[0], loss.detach())
    assert m.loss({**hidden, "mask": None}, *none)[0] > loss + 1


@pytest.mark.parametrize("kind", ["spherical", "planar"])
def test_detectors_learn_a_batch(kind):
    torch.manual_seed(0)
    classes = torch.tensor([0, 1, 2, 0, 1, 2])
    image = torch.tensor([0, 0, 0, 1, 1, 1])
    if kind == "spherical":
        m = SphericalDetector(**SMALL)
        x = torch.randn(2, len(grids.icosahedral(3).pos), 3)
    else:
        m = PlanarDetector(num_classes=3, height=32, width=64, channels=(4, 8))
        x = torch.randn(2, 3, 32, 64)
    opt = torch.optim.Adam(m.parameters(), 1e-2)
    losses = []
    for _ in range(30):
        loss, stats = m.loss(m(x), BOXES.float(), classes, image)
        opt.zero_grad()
        loss.backward()
        opt.step()
        losses.append(loss.item())
    assert all(np.isfinite(v) for v in stats.values())
    assert losses[-1] < 0.5 * losses[0]


@pytest.mark.parametrize("kind", ["spherical", "planar"])
def test_detector_losses_refuse_boxes_that_do_not_fit_the_batch(kind):
    if kind == "spherical":
        m, x = SphericalDetector(**SMALL), torch.randn(2, len(grids.icosahedral(3).pos), 3)
    else:
        m, x = PlanarDetector(num_classes=3, height=32, width=64, channels=(4, 8)), torch.randn(2, 3, 32, 64)
    out, b = m(x), BOXES[:2].float()
    for classes, image, said in [
            ((0, 3), (0, 1), r"classes must be in \[0, 3\), got 0 to 3"),
            ((0, -1), (0, 1), r"got -1 to 0"),  # used to wrap around to the last class
            ((0, 1), (0, 2), r"image indices must be in \[0, 2\)"),
            ((0,), (0, 1), r"need boxes \[K, 5\], classes \[K\]")]:  # used to be cut short
        with pytest.raises(ValueError, match=said):
            m.loss(out, b, torch.tensor(classes), torch.tensor(image))


@pytest.mark.parametrize("kind", ["spherical", "planar"])
def test_heatmaps_start_at_centernets_prior_after_every_reset(kind):
    if kind == "spherical":
        m = SphericalDetector(**SMALL)
        bias = lambda: m.head.bias  # noqa: E731
    else:
        m = PlanarDetector(num_classes=3, height=32, width=64, channels=(4, 8))
        bias = lambda: m.body.head[-1].bias  # noqa: E731
    for _ in range(2):
        np.testing.assert_allclose(torch.sigmoid(bias()[:3]).detach(), 0.01, rtol=0.01)
        assert bias()[3:].abs().max() < 1  # the boxes' biases: as initialized
        with torch.no_grad():
            bias().fill_(3.0)
        m.reset_parameters()


def test_planar_detector_checks_its_sizes_and_spaces_its_targets_by_its_pixels():
    with pytest.raises(ValueError, match="height and width must be divisible by 4, got 30x64"):
        PlanarDetector(num_classes=3, height=30, width=64, channels=(4, 8, 8))
    with pytest.raises(ValueError, match="height and width must be divisible by 4, got 32x66"):
        PlanarDetector(num_classes=3, height=32, width=66, channels=(4, 8, 8))
    m = PlanarDetector(num_classes=3, height=32, width=64, channels=(4, 8, 8))
    for bad in ((1, 3, 32, 32), (1, 1, 32, 64), (3, 32, 64)):
        with pytest.raises(ValueError, match=r"expected x \[B, 3, 32, 64\]"):
            m(torch.rand(bad))
    # the heatmaps' Gaussians are sized in output pixels: one is pi / 16 of latitude here
    grid = m.points.reshape(16, 32, 3)
    np.testing.assert_allclose(m.spacing, torch.acos(grid[:-1, 0] @ grid[1:, 0].T).diagonal(), rtol=1e-6)
    assert m.spacing == pytest.approx(math.pi / 16)


def test_detector_errors_and_masks():
    m = SphericalDetector(**SMALL)
    n = len(grids.icosahedral(3).pos)
    with pytest.raises(ValueError, match=r"expected x \[B, 642, 3\]"):
        m(torch.randn(1, 100, 3))
    with pytest.raises(ValueError, match="NaN"):
        m(torch.full((1, n, 3), float("nan")))
    with pytest.raises(ValueError, match="some point visible"):
        m(torch.randn(1, n, 3), torch.zeros(n, dtype=torch.bool))
    with pytest.raises(ValueError, match="min_level <= head_level"):
        SphericalDetector(input_level=3, head_level=4, min_level=1, channels=(4, 6, 8))
    with pytest.raises(ValueError, match="upright_convs reads up"):
        SphericalDetector(**SMALL, gravity=True, upright_convs=2)
    mask = grids.icosahedral(3).pos[:, 0] > 0  # a forward hemisphere
    out = m(torch.randn(2, n, 3), mask)
    hidden = ~out["mask"]
    assert hidden.any() and out["mask"].any()
    det = m.detect(torch.randn(n, 3), mask, threshold=0.0, k=50, nms=None)[0]
    centres = m.head_pos[[int(np.argmax(m.head_pos.numpy() @ np.array(
        [np.cos(b[1]) * np.cos(b[0]), np.cos(b[1]) * np.sin(b[0]), np.sin(b[1])]))) for b in det["boxes"]]]
    assert len(det["boxes"]) and (centres[:, 0] > -0.5).all()  # peaks only where the camera sees


@pytest.mark.parametrize("kind", ["spherical", "planar"])
def test_decode_drops_boxes_centred_where_the_camera_does_not_see(kind):
    """A camera that sees the half x > 0: the boxes centred in the other half go, the
    rest stay; ``drop_hidden=False`` keeps all. The centres are 4.6 degrees or more from
    the border, over the input's spacing."""
    classes = torch.tensor([0, 1, 2, 0, 1, 2])
    boxes = BOXES.clone()
    boxes[:, 4] = torch.tensor([0.0, 0.0, 0.3, -0.4, 0.5, 0.0])  # the planar one's rolls
    if kind == "spherical":
        m = SphericalDetector(**SMALL).double()
        out, pos = _perfect_fields(m, boxes, classes), grids.icosahedral(3).pos
    else:
        m = PlanarDetector(num_classes=3, height=64, width=128, channels=(4, 8)).double()
        out, pos = _planar_perfect_fields(m, boxes, classes), m.input_pos
    out["seen"] = pos[:, 0] > 0
    want = np.sort(boxes[box_centres(boxes)[:, 0] > 0, 0].numpy())
    assert len(want) == 3
    kept = m.decode(out, threshold=0.5)[0]["boxes"]
    np.testing.assert_allclose(np.sort(kept[:, 0]), want, atol=1e-9)
    assert len(m.decode(out, threshold=0.5, drop_hidden=False)[0]["boxes"]) == 6
    assert int(m.decode_image(fields_on_cpu(out), 0, threshold=0.5)[3].sum()) == 3  # its default too
    # a field of view per image: the second sees the other half
    two = {k: torch.cat([v, v]) if torch.is_tensor(v) and v.dim() > 1 else v for k, v in out.items()}
    two["seen"] = torch.stack([out["seen"], ~out["seen"]])
    first, second = m.decode(two, threshold=0.5)
    np.testing.assert_allclose(np.sort(first["boxes"][:, 0]), want, atol=1e-9)
    other = np.sort(boxes[box_centres(boxes)[:, 0] < 0, 0].numpy())
    np.testing.assert_allclose(np.sort(second["boxes"][:, 0]), other, atol=1e-9)


def test_hidden_boxes_are_dropped_before_nms():
    """Two overlapping boxes of a class, the better one centred where the camera does not
    see: the other one is kept, not suppressed by it."""
    m = SphericalDetector(num_classes=3, input_level=3, head_level=3, min_level=1, channels=(4, 6, 8),
                          pairs=2, gradient_fields=2).double()
    boxes = torch.tensor(np.radians([[84.0, 0, 40, 40, 0], [96, 0, 40, 40, 0]]))
    assert box_iou(boxes[:1], boxes[1:], dtype=torch.float64).item() > 0.5
    out = _perfect_fields(m, boxes, torch.tensor([0, 0]))
    hidden = nearest_points(boxes[1:], m.head_pos)
    out["heat"][0, hidden, 0] = 30.0  # the hidden box scores higher
    out["seen"] = grids.icosahedral(3).pos[:, 0] > 0
    kept = m.decode(out, threshold=0.5)[0]["boxes"]
    assert len(kept) == 1 and np.degrees(kept[0, 0]) < 90
    every = m.decode(out, threshold=0.5, drop_hidden=False)[0]["boxes"]
    assert len(every) == 1 and np.degrees(every[0, 0]) > 90  # NMS keeps the better one


def test_heatmap_targets_against_a_loop_over_boxes_and_points():
    """Two images, seven boxes of three classes, sigmas on both sides of the half-spacing
    floor: the heatmaps, centre points and regression samples written out box by box."""
    gen = torch.Generator().manual_seed(3)
    points = grids.icosahedral(3).pos.double()
    K, B, C, h = 7, 2, 3, 0.1
    r = torch.rand(K, 5, generator=gen, dtype=torch.float64)
    boxes = torch.stack([2 * math.pi * r[:, 0] - math.pi, 2.4 * (r[:, 1] - 0.5), 0.1 + 1.4 * r[:, 2],
                         0.1 + 1.4 * r[:, 3], r[:, 4] - 0.5], 1)
    classes = torch.tensor([0, 2, 2, 1, 0, 2, 1])
    image = torch.tensor([0, 0, 1, 1, 0, 1, 0])
    target, nearest, (pt, bx, w) = heatmap_targets(points, boxes, classes, image, B, C, h)
    P = points.numpy()
    want, g = np.zeros((B, len(P), C)), np.zeros((K, len(P)))
    sigmas = []
    for k, (lon, lat, fx, fy, _) in enumerate(boxes.tolist()):
        c = np.array([math.cos(lat) * math.cos(lon), math.cos(lat) * math.sin(lon), math.sin(lat)])
        sigma = max(0.1 * math.sqrt(fx * fy), h / 2)
        sigmas.append(sigma)
        g[k] = np.exp(-np.arccos(np.clip(P @ c, -1, 1)) ** 2 / (2 * sigma ** 2))
        assert nearest[k] == np.argmax(P @ c)
        g[k, np.argmax(P @ c)] = 1.0
        want[image[k], :, classes[k]] = np.maximum(want[image[k], :, classes[k]], g[k])
    assert min(sigmas) == h / 2 < max(sigmas)
    np.testing.assert_allclose(target.numpy(), want, rtol=0, atol=1e-12)
    samples = set()
    for b in range(B):
        mine = np.flatnonzero(image.numpy() == b)
        top = g[mine].max(0)
        for k in mine:
            samples |= {(q, k) for q in np.flatnonzero((g[k] >= top) & (g[k] >= 0.05))}
    got = {(q, k) for q, k in zip(pt.tolist(), bx.tolist())}
    assert len(got) == len(pt) and got == samples and len(samples) > 30
    np.testing.assert_allclose(w.numpy(), g[bx.numpy(), pt.numpy()], rtol=0, atol=1e-12)


def test_focal_loss_against_the_formula_written_out():
    """CenterNet's loss element by element (alpha 2, beta 4 by default), hidden points
    left out, over the number of positives (1 when there are none)."""
    gen = torch.Generator().manual_seed(0)
    logits = 3 * torch.randn(2, 40, 3, generator=gen, dtype=torch.float64)
    target = torch.rand(2, 40, 3, generator=gen, dtype=torch.float64) * 0.9
    target[0, 3, 1] = target[1, 7, 0] = target[1, 30, 2] = 1.0
    mask = torch.rand(2, 40, generator=gen) > 0.3
    mask[1, 30] = False  # a hidden positive counts, as CenterNet counts every centre

    def reference(logits, target, mask, a, b):
        total, npos = 0.0, 0
        for i, j, k in np.ndindex(*logits.shape):
            p, y = 1 / (1 + math.exp(-float(logits[i, j, k]))), float(target[i, j, k])
            npos += y == 1.0
            if mask is None or mask[i, j]:
                total += (1 - p) ** a * math.log(p) if y == 1.0 else (1 - y) ** b * p ** a * math.log(1 - p)
        return -total / max(npos, 1)

    assert float(focal_loss(logits, target, mask)) == pytest.approx(reference(logits, target, mask, 2, 4), rel=1e-12)
    assert float(focal_loss(logits, target, None, alpha=1.0, beta=2.0)) == pytest.approx(
        reference(logits, target, None, 1, 2), rel=1e-12)
    none = target.clamp(max=0.9)
    assert float(focal_loss(logits, none)) == pytest.approx(reference(logits, none, None, 2, 4), rel=1e-12)


def test_spherical_detector_loss_is_its_parts_written_out():
    """The focal loss plus smooth-L1 terms (offset in spacings with beta 1, mean log size
    and the two shape fields with beta 0.1), weighted by the regression samples' shares;
    one box has them too, no box only the focal term. The grids' positions are geometry,
    not state: a checkpoint does not hold them."""
    torch.manual_seed(1)
    m = SphericalDetector(**SMALL).double()
    assert not {"head_pos", "input_pos"} & set(m.state_dict())
    with torch.no_grad():
        out = m(torch.randn(2, len(grids.icosahedral(3).pos), 3, dtype=torch.float64))

    def sl1(e, beta):
        return torch.where(e.abs() < beta, 0.5 * e ** 2 / beta, e.abs() - 0.5 * beta)

    for k in (6, 1):
        boxes, classes, image = BOXES[:k], torch.tensor([0, 1, 2, 0, 1, 2])[:k], torch.tensor([0, 0, 0, 1, 1, 1])[:k]
        total, parts = m.loss(out, boxes, classes, image)
        t = m.targets(boxes, classes, image, 2)
        w, at = t["weight"] / t["weight"].sum(), (t["image"], t["point"])
        want = {"heat": float(focal_loss(out["heat"], t["heat"], None)),
                "offset": float((w * sl1((out["offset"][at] - t["offset"]).norm(dim=-1) / m.head_spacing, 1.0)).sum()),
                "size": float((w * sl1(out["s"][at] - t["s"], 0.1)).sum()),
                "shape": float((w * sl1((out["dev"][at] - t["dev"]).norm(dim=-1), 0.1)).sum()
                               + (w * sl1((out["quad"][at] - t["quad"]).norm(dim=-1), 0.1)).sum())}
        assert parts == pytest.approx(want, rel=1e-12) and min(want.values()) > 0
        assert float(total) == pytest.approx(sum(want.values()), rel=1e-12)
    total, parts = m.loss(out, BOXES[:0], torch.zeros(0, dtype=torch.long), torch.zeros(0, dtype=torch.long))
    assert parts["offset"] == parts["size"] == parts["shape"] == 0.0 and float(total) == pytest.approx(parts["heat"])
