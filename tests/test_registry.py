"""The generic registry (radfield.util.registry) that the primitive kinds and the dataset formats
are kept in: names, order, the duplicate and unknown-name errors. Its users' own behaviour is
tests/test_kinds.py's and tests/test_dataset_formats.py's."""

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
    with pytest.raises(RadfieldError, match=r"\(known: first, tie1, tie2, late\)$"):
        things.get("nope")
