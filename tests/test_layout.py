"""Layout (dsl/layout.py): pack/unpack round trips, errors, extension by passes, manifests."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from balustrade.dsl import OCP, Layout
from balustrade.errors import BalustradeError, NonFiniteError, ShapeError

shapes = st.lists(st.tuples(st.integers(1, 3), st.integers(1, 3)), min_size=0, max_size=4)


def _layout(shape_list, noun="variable"):
    return Layout.stack(((f"v{k}", s, np.full(s, float(k)), None, None)
                         for k, s in enumerate(shape_list)), owner="t", noun=noun)


@settings(max_examples=60, deadline=None)
@given(shapes, st.integers(0, 2**31 - 1))
def test_pack_unpack_round_trip(shape_list, seed):
    lay = _layout(shape_list)
    w = np.random.default_rng(seed).normal(size=lay.size)
    values = lay.unpack(w)
    assert list(values) == [f"v{k}" for k in range(len(shape_list))]
    for arr, s in zip(values.values(), shape_list):
        assert arr.shape == ((s[0],) if s[1] == 1 else s)
    np.testing.assert_array_equal(lay.pack(values), w)
    # missing values take their init, stacked column-major in order
    np.testing.assert_array_equal(lay.pack({}), np.concatenate(
        [np.full(r * c, float(k)) for k, (r, c) in enumerate(shape_list)] or [np.zeros(0)]))


def test_layout_matches_ocp_flattening():
    ocp = OCP(name="o")
    ocp.variable("a", 2, 3, lb=-1, ub=np.arange(6).reshape(2, 3), init=0.5)
    ocp.variable("b", 1)
    ocp.parameter("p", 2, 2, value=np.eye(2))
    lay = ocp.variable_layout
    assert lay.slices == {"a": slice(0, 6), "b": slice(6, 7)}
    lb, ub = ocp.bounds()
    np.testing.assert_array_equal(ub[:6], np.arange(6).reshape(2, 3).reshape(-1, order="F"))
    np.testing.assert_array_equal(lb, [-1] * 6 + [-np.inf])
    np.testing.assert_array_equal(ocp.pack_parameters({}), [1, 0, 0, 1])
    ocp.variable("c", 2)  # the cached layout follows new declarations
    assert ocp.variable_layout.size == 9


def test_errors_name_the_block():
    ocp = OCP(name="o")
    ocp.variable("a", 2)
    ocp.parameter("x0", 2)
    with pytest.raises(ShapeError, match=r"o: parameter 'x0': expected shape \(2, 1\)"):
        ocp.pack_parameters({"x0": np.zeros(3)})
    with pytest.raises(NonFiniteError, match="o: parameter 'x0'"):
        ocp.pack_parameters({"x0": [np.nan, 0]})
    with pytest.raises(BalustradeError, match="no value for parameter 'x0'"):
        ocp.pack_parameters({})
    with pytest.raises(BalustradeError, match="unknown parameters 'y'"):
        ocp.pack_parameters({"y": 1})
    with pytest.raises(BalustradeError, match="parameter values must be a dict"):
        ocp.pack_parameters([1, 2])
    with pytest.raises(ShapeError, match="o: initial guess 'a'"):
        ocp.pack_variables({"a": np.zeros((2, 2))})
    with pytest.raises(ShapeError, match=r"stacked decision vector: expected shape \(2,\)"):
        ocp.unpack_variables(np.zeros(3))


def test_extend_adds_blocks_after_the_users():
    lay = _layout([(2, 1), (1, 2)])
    ext = lay.extend("epi:0", (3, 1), init=0.0, lb=0.0, origin="epigraph")
    assert (ext.size, ext.user_size, lay.size) == (7, 4, 4)  # lay itself is unchanged
    assert [e.name for e in ext.added] == ["epi:0"]
    lb, ub = ext.bounds()
    np.testing.assert_array_equal(lb[4:], 0.0)
    assert np.all(np.isinf(ub))
    w = np.arange(7.0)
    assert set(ext.unpack(w, user_only=True)) == {"v0", "v1"}
    np.testing.assert_array_equal(ext.pack({"v0": [5, 6]})[4:], 0.0)
    with pytest.raises(BalustradeError, match="unknown variables 'epi:0'"):
        ext.pack({"epi:0": np.zeros(3)})  # added blocks are not the user's to set
    with pytest.raises(BalustradeError, match="already has a block"):
        ext.extend("v0", (1, 1), origin="epigraph")
    with pytest.raises(BalustradeError, match="origin other than 'user'"):
        lay.extend("t", (1, 1), origin="user")


def test_manifest_round_trip_keeps_defaults_and_checks():
    lay = Layout.stack([("x0", (2, 1), None, None, None), ("q", (1, 1), np.array([[3.0]]),
                                                            None, None)],
                       owner="P", noun="parameter")
    back = Layout.from_dict(lay.to_dict(), owner="P", noun="parameter")
    assert back.slices == lay.slices
    np.testing.assert_array_equal(back.pack({"x0": [1, 2]}), [1, 2, 3])
    with pytest.raises(BalustradeError, match="P: no value for parameter 'x0'"):
        back.pack({})
    with pytest.raises(BalustradeError, match="expected 0"):
        Layout.from_dict({"a": {"offset": 1, "shape": [1, 1]}})
