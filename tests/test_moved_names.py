"""Names that moved in the restructuring of issue #13 (solvers and algorithms out of
``problems/``, examples out of ``models/``/``learn/``): importing one from its old module is
a :class:`~balustrade.errors.MovedError` naming the new home, and the new home has it."""

from __future__ import annotations

import importlib

import pytest

from balustrade.errors import BalustradeError, MovedError

OLD_MODULES = ["balustrade.problems.terminal_cbf", "balustrade.problems.rpi",
               "balustrade.dsl.error_sets", "balustrade.problems.robust",
               "balustrade.problems.approximate", "balustrade.problems.regret",
               "balustrade.problems.regret.synthesis", "balustrade.learn.sampler",
               "balustrade.models.bicycle"]


def moves() -> list[tuple[str, str, str]]:
    out = []
    for old in OLD_MODULES:
        mod = importlib.import_module(old)
        out += [(old, name, new) for name, new in mod.__getattr__.moved.items()]
    return out


@pytest.mark.parametrize("old,name,new", moves())
def test_old_import_says_where_the_name_lives_and_it_lives_there(old, name, new):
    with pytest.raises(MovedError, match=rf"{old}\.{name} moved to {new}\.{name}"):
        exec(f"from {old} import {name}", {})
    assert hasattr(importlib.import_module(new), name), f"{new} has no {name}"


def test_moved_error_is_an_import_error_and_a_balustrade_error():
    with pytest.raises(ImportError):
        from balustrade.problems.terminal_cbf import synthesize_terminal_cbf  # noqa: F401
    assert issubclass(MovedError, BalustradeError)


def test_other_missing_names_are_still_attribute_errors():
    mod = importlib.import_module("balustrade.problems.regret")
    assert not hasattr(mod, "no_such_name")
