"""The mutation runner (tests/mutations.py) stays usable: every patch still applies to today's code.

The runner itself takes minutes per mutation and is run by hand; this file only checks, in a
fraction of a second, that each mutation's anchor text still matches the expected number of times
and that the patched source compiles. When a model file is refactored this fails and names the
mutation to update, instead of the runner finding out later.
"""

from __future__ import annotations

import pytest

import mutations as mut


def test_every_mutation_applies_to_the_current_code() -> None:
    """Catches: model code moved or renamed so that a mutation's anchor no longer matches (the
    runner would report ANCHOR for it instead of testing it)."""
    problems = mut.check_anchors()
    assert not problems, "\n".join(f"{m.name}: {msg}" for m, msg in problems)


def test_mutation_names_are_unique_and_families_have_test_files() -> None:
    """Catches: two mutations with one name (one verdict would hide the other) and a family whose
    test-file pattern matches no file (its mutations would run only the common tests)."""
    names = [m.name for m in mut.MUTATIONS]
    assert len(names) == len(set(names))
    files = mut.source_files()
    for family in {m.family for m in mut.MUTATIONS}:
        own = [f for f in mut.test_files(family, files) if f not in mut.COMMON_TESTS]
        assert own, f"no tests/test_model_{family}*.py file"


def test_anchor_mismatch_is_loud() -> None:
    """Catches: a missing or ambiguous anchor being skipped or half applied instead of reported."""
    edit = mut.Edit("x.py", "a = 1", "a = 2")
    assert mut.patched("a = 1\n", edit) == "a = 2\n"
    with pytest.raises(mut.AnchorError, match="found 0 time"):
        mut.patched("b = 1\n", edit)
    with pytest.raises(mut.AnchorError, match="found 2 time"):
        mut.patched("a = 1\na = 1\n", edit)
    assert mut.patched("a = 1\na = 1\n", mut.Edit("x.py", "a = 1", "a = 2", count=2)) == "a = 2\na = 2\n"
