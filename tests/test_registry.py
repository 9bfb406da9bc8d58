"""The generic registry (radfield.util.registry) that every extension point keeps its things in
(primitive kinds, dataset formats, backends, edit operations, stages, commands, demo scenes):
names, order, the duplicate and unknown-name errors. Its users' own behaviour is their tests'
(tests/test_kinds.py, test_dataset_formats.py, test_backends.py, ...)."""

import pytest

from radfield.errors import RadfieldError
from radfield.util.registry import Registry


def test_registration_order_duplicates_and_unknown_names():
    things = Registry("widget")
    assert things.names() == () and things.values() == ()
    assert things.register("b", 2) == 2 and things.register("a", 1) == 1
    assert things.names() == ("b", "a") and things.values() == (2, 1) and "a" in things and "c" not in things
    with pytest.raises(ValueError, match=r"^widget 'a' is registered already$"):
        things.register("a", 3)
    assert things.get("a") == 1   # the refused registration replaced nothing
    with pytest.raises(RadfieldError, match=r"^unknown widget 'c' \(known: b, a\)$"):
        things.get("c")
    things.unregister("b")
    things.unregister("b")        # forgetting what is not there is no error (clean-ups call it)
    assert things.names() == ("a",)


def test_an_order_key_sorts_names_and_values_and_keeps_ties_in_registration_order():
    things = Registry("format", order=lambda thing: thing[0])
    for name, priority in (("late", 9), ("first", 1), ("tie1", 5), ("tie2", 5)):
        things.register(name, (priority, name))
    assert things.names() == ("first", "tie1", "tie2", "late")
    assert [name for _, name in things.values()] == list(things.names())
    assert things.items() == tuple(zip(things.names(), things.values()))
    with pytest.raises(RadfieldError, match=r"\(known: first, tie1, tie2, late\)$"):
        things.get("nope")


def test_every_extension_point_is_a_registry_in_its_order():
    """One style for every seam: each extension point's things are a Registry, listed in the order
    the rest of radfield uses them (the backends best first with the torch twins last, the stages
    in pipeline order, the commands in `radfield --help` order, the operations a spec may name)."""
    from radfield.cli.main import COMMANDS, app, command_names
    from radfield.core.backends import seam
    from radfield.edit import spec
    from radfield.stages.registry import STAGES, stages

    assert isinstance(seam._BACKENDS, Registry) and seam.names()[-1] == seam.TORCH
    assert seam.names()[:2] == [seam.FUSED_CPU, seam.TRITON]
    assert isinstance(STAGES, Registry) and [stage.name for stage in stages()] == list(STAGES.names())
    assert STAGES.names() == ("sfm", "data", "triangulate", "envelope", "tetra", "init", "train", "bind", "bake", "eval")
    assert isinstance(COMMANDS, Registry) and command_names(app) == list(COMMANDS.names())
    assert isinstance(spec.OPERATIONS, Registry) and set(spec.registry()) == set(spec.OPERATIONS.names())
    with pytest.raises(ValueError, match=r"^edit operation 'transform' is registered already$"):
        spec.operation("transform")(lambda fld, args, ctx: fld)


def test_the_torch_twins_stay_last_whatever_a_backend_ranks():
    from radfield.core.backends import seam

    seam.register(seam.Backend("test-late", lambda device, dtype: True, rank=10**9))
    try:
        assert seam.names()[-2:] == ["test-late", seam.TORCH]
        with pytest.raises(ValueError, match=r"^backend 'test-late' is registered already$"):
            seam.register(seam.Backend("test-late", lambda device, dtype: True))
    finally:
        seam.unregister("test-late")
    assert "test-late" not in seam.names()
