"""Kinds, tags, roles and statuses are str enums: strings, f-strings and JSON keep working."""

from __future__ import annotations

import json

import numpy as np
import pytest

from balustrade.backends import Solution, Status
from balustrade.dsl import OCP, BlockKind, BlockTag, TermKind, VariableRole, norm
from balustrade.errors import BalustradeError


def _sol(status):
    return Solution(status, 0.0, {"a": np.zeros(1)}, {}, 0.0, 0, "none", "none")


def test_str_compatibility():
    ocp = OCP(name="e")
    a = ocp.variable("a", 2, role="slack")
    blk = ocp.le(a, 1.0, name="box", tag="state")
    ocp.minimize(norm(a, 2))
    v, term = ocp.variables["a"], ocp.cost.terms[0]
    assert v.role is VariableRole.SLACK and v.role == "slack"
    assert blk.kind is BlockKind.LE and blk.kind == "le" and blk.tag is BlockTag.STATE
    assert term.kind is TermKind.NORM2 and term.kind == "norm2" and f"{term.kind}#0" == "norm2#0"
    assert json.dumps({"k": term.kind, "t": blk.tag}) == '{"k": "norm2", "t": "state"}'
    assert TermKind.NORM1.nonsmooth and not TermKind.SQUARED2.nonsmooth


def test_status_from_strings():
    s = _sol("optimal")
    assert s.status is Status.OPTIMAL and s.status == "optimal" and s.success
    assert f"slack_{s.status}" == "slack_optimal" and json.dumps(s.status) == '"optimal"'
    s.status = "feasible"
    assert s.status is Status.FEASIBLE and s.usable and not s.success
    assert {m.value for m in Status} >= {"optimal", "optimal_inaccurate", "feasible",
                                         "infeasible", "unbounded", "max_iterations", "failed"}


def test_unknown_values_are_refused_by_name():
    with pytest.raises(BalustradeError, match="unknown status 'candidate'"):
        _sol("candidate")
    ocp = OCP(name="e")
    with pytest.raises(BalustradeError, match="e: variable 'a': role: unknown VariableRole"):
        ocp.variable("a", 1, role="slak")
    b = ocp.variable("b", 1)
    with pytest.raises(BalustradeError, match="e: block 'c': tag: unknown BlockTag 'stat'"):
        ocp.le(b, 0.0, name="c", tag="stat")
