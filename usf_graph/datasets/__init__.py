"""PyG datasets for the tasks."""

from .mnist import SphericalMNIST, load_digits, read_idx, read_mnist_csv

__all__ = ["SphericalMNIST", "load_digits", "read_idx", "read_mnist_csv"]
