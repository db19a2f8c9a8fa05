"""Names that moved in the restructuring of issue #13 (solvers and algorithms out of
``problems/``, examples out of ``models/``/``learn/``): importing one from its old module
still gives the object, with a DeprecationWarning naming the new home."""

from __future__ import annotations

import importlib

import pytest

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
def test_old_import_warns_and_gives_the_object_of_the_new_home(old, name, new):
    scope: dict = {}
    with pytest.warns(DeprecationWarning, match=rf"{old}\.{name} moved to {new}\.{name}"):
        exec(f"from {old} import {name}", scope)
    assert scope[name] is getattr(importlib.import_module(new), name)


def test_other_missing_names_are_still_attribute_errors():
    mod = importlib.import_module("balustrade.problems.regret")
    assert not hasattr(mod, "no_such_name")
    with pytest.raises(ImportError):
        exec("from balustrade.problems.regret import no_such_name", {})
