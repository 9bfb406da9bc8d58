"""Datasets: image I/O, readers for NeRF-synthetic / nerfstudio / COLMAP / photo folders, and
synthetic scenes with exact ground truth."""

from radfield.datasets.images import image_size, read_image, resize_area, write_image
from radfield.datasets.readers import (
    FORMATS,
    SPLITS,
    Dataset,
    Points,
    View,
    detect_format,
    list_images,
    load_dataset,
    validate,
)

__all__ = [
    "FORMATS",
    "SPLITS",
    "Dataset",
    "Points",
    "View",
    "detect_format",
    "image_size",
    "list_images",
    "load_dataset",
    "read_image",
    "resize_area",
    "validate",
    "write_image",
]
