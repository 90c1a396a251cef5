"""Handing known gravity to a batch (train.gravity)."""

import pytest
import torch

from usf_graph.train.gravity import given_up, views_up


def test_given_up_hands_one_or_each_views_gravity_to_a_batch():
    x = torch.zeros(2, 5, 3, dtype=torch.float64)
    assert given_up(None, x) == {}
    z = torch.tensor([0.0, 0.0, 1.0])
    one = given_up(z, x)["up"]
    assert one.shape == (2, 3) and one.dtype == torch.float64 and (one == z.double()).all()
    split = torch.arange(12.0).view(4, 3)  # one per view of a 4-view split
    assert torch.equal(given_up(split, x, 1)["up"], split[1:3].double())
    assert torch.equal(given_up(split, x[:1], 3)["up"], split[3:].double())


def test_views_up_needs_a_split_that_knows_its_gravity():
    class Views:
        gravity = torch.eye(3)

    assert torch.equal(views_up(Views()), torch.eye(3))
    with pytest.raises(ValueError, match="does not know its views' gravity"):
        views_up(object())
