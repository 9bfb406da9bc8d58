"""The primitive-kind registry: the one place that says what a kind of primitive is.

    kinds.get("neural"), kinds.of(prims)   the PrimitiveKind of a name or of a primitives object
    kinds.names()                          the registered kinds ("neural", "gaussian", "neural-dynamic",
                                           "gaussian-dynamic", "neural-relight", "gaussian-relight",
                                           then any added)
    kinds.register(kind), unregister(name) add a kind (a PrimitiveKind subclass instance, kinds/base.py)

Built in: splattable neural primitives (kinds/neural.py), 3D Gaussians (kinds/gaussian.py), and
their time-conditioned variants for dynamic scenes (kinds/dynamic.py; `kind.conditions` says that
a view must give a time) and their relightable variants for one-light-at-a-time captures
(kinds/relight.py; a view must give a light).
A new kind is one module that defines its primitives dataclass (a `Primitives` subclass), a
`PrimitiveKind` subclass with the hooks it needs, registers it, and registers its fast renderers
with radfield.core.backends; training, the model file, rendering, editing and export then take it
(tests/test_kinds.py adds one inside a test). Every kind is also declared as an entry point of the
group radfield.kinds (pyproject.toml), which is how `reconstruct --help` lists the kinds without
importing them and how a kind of another installed package is found (_load_declared_kinds).
"""

from radfield.core.geometry.rotations import quat_to_rotmat, rotmat_to_quat
from radfield.core.kinds.base import (INITIAL_ALPHA, PixelRay, PrimitiveKind, Primitives, get, names, of, register,
                                      registered, unregister)
from radfield.core.kinds.neural import DEFAULT_HIDDEN, DEFAULT_OMEGA0, NeuralPrimitives, random_neural, siren_mlp_init
from radfield.core.kinds.neural_density import density_window, ellipsoid_radius_sq
from radfield.core.kinds.gaussian import Gaussians, random_gaussians
from radfield.core.kinds.dynamic import DynamicGaussians, DynamicNeuralPrimitives
from radfield.core.kinds.relight import RelightGaussians, RelightNeuralPrimitives
from radfield.core.splat.kernels import WINDOW_GAIN


def _load_declared_kinds() -> None:
    """The kinds other installed packages declare (entry points of the group radfield.kinds, as
    pyproject.toml declares the built-in ones): loading one imports its module, which registers it.
    A package whose kind fails to import is named in one warning; the rest of radfield works."""
    import warnings
    from importlib.metadata import entry_points

    for point in entry_points(group="radfield.kinds"):
        if point.name not in names():
            try:
                point.load()
            except Exception as error:  # a broken plugin must not break radfield
                warnings.warn(f"radfield: the primitive kind {point.name!r} ({point.value}) failed to load: "
                              f"{type(error).__name__}: {error}", RuntimeWarning, stacklevel=2)


_load_declared_kinds()

__all__ = ["DEFAULT_HIDDEN", "DEFAULT_OMEGA0", "INITIAL_ALPHA", "WINDOW_GAIN", "DynamicGaussians",
           "DynamicNeuralPrimitives", "Gaussians", "NeuralPrimitives", "RelightGaussians", "RelightNeuralPrimitives",
           "PixelRay", "PrimitiveKind", "Primitives", "density_window",
           "ellipsoid_radius_sq", "get", "names", "of", "quat_to_rotmat", "random_gaussians", "random_neural",
           "register", "registered", "rotmat_to_quat", "siren_mlp_init", "unregister"]
