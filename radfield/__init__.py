"""radfield: editable radiance fields made of splattable neural primitives."""

__version__ = "0.1.0"
