"""Property tests (audit E, session 15) for bad input on the parameters session 14 added:
the DAQP engine's options (``kkt_tol`` and DAQP's settings), ``OCP.parameter(lb=)`` packing,
``check_deltas`` (SPEC §1.4) and ``check_stall_stop``. Each property states the rule
independently of the implementation: accepted exactly when the rule holds, else a
:class:`~balustrade.errors.BalustradeError` before any solver runs."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from balustrade._checks import check_deltas
from balustrade.backends import compile
from balustrade.backends.stall import check_stall_stop
from balustrade.dsl import OCP, squared_norm
from balustrade.errors import BalustradeError

pytest.importorskip("daqp")

_ANY = st.one_of(st.floats(allow_nan=True, allow_infinity=True), st.integers(-5, 5),
                 st.booleans(), st.text(max_size=3), st.none())


def _qp(lb: float | None = None) -> OCP:
    ocp = OCP(name="qp")
    y = ocp.variable("y", 2)
    c = ocp.parameter("c", 2, lb=lb)
    ocp.le(y, 1.0, name="upper")
    ocp.minimize(squared_norm(y - c))
    return ocp


@settings(max_examples=40, deadline=None)
@given(tol=_ANY)
def test_kkt_tol_is_a_finite_positive_number(tol):
    """``kkt_tol`` accepted iff a real number (not a bool), finite and > 0; ``inf`` would
    switch the KKT check off (it was accepted before audit E, as were ``"1e-8"`` and
    ``True``)."""
    ok = (isinstance(tol, int | float) and not isinstance(tol, bool)
          and bool(np.isfinite(tol)) and tol > 0)
    if ok:
        sol = compile(_qp(), "fast-convex-daqp", options={"kkt_tol": tol}).solve(
            {"c": [2.0, 0.0]})
        assert sol.status == "optimal"
    else:
        with pytest.raises(BalustradeError, match="kkt_tol"):
            compile(_qp(), "fast-convex-daqp", options={"kkt_tol": tol})


@settings(max_examples=30, deadline=None)
@given(value=_ANY)
def test_daqp_settings_are_real_numbers(value):
    """A DAQP setting that is not a real number (NaN, a bool, a string, None) is refused by
    name; a NaN ``primal_tol`` used to reach DAQP and fail every solve over to PIQP."""
    ok = (isinstance(value, int | float) and not isinstance(value, bool)
          and not np.isnan(value))
    if ok:
        compile(_qp(), "fast-convex-daqp", options={"primal_tol": value})
    else:
        with pytest.raises(BalustradeError, match="primal_tol"):
            compile(_qp(), "fast-convex-daqp", options={"primal_tol": value})


@settings(max_examples=60, deadline=None)
@given(lb=st.floats(-1e6, 1e6), gap=st.floats(-1e-6, 1e-6))
def test_parameter_lower_bound_packing(lb, gap):
    """``OCP.parameter(lb=)``: a value ``v`` is packed as ``max(v, lb)`` when
    ``v >= lb − 1e-9·max(1, |lb|)`` (a rounding of the bound), else refused naming the
    parameter; the packed value is never below ``lb``."""
    ocp = _qp(lb)
    v = lb + gap * max(1.0, abs(lb))
    if v >= lb - 1e-9 * max(1.0, abs(lb)):
        packed = ocp.pack_parameters({"c": [v, v]})
        assert np.all(packed >= lb) and np.allclose(packed, max(v, lb), rtol=0, atol=0)
    else:
        with pytest.raises(BalustradeError, match="'c'"):
            ocp.pack_parameters({"c": [v, v]})


@settings(max_examples=80, deadline=None)
@given(d=st.lists(st.one_of(st.floats(-2, 5), st.sampled_from([0.0, np.nan, np.inf])),
                  min_size=3, max_size=3))
def test_check_deltas_is_spec_1_4(d):
    """``check_deltas``: accepted iff finite, ``Δ_0 = 0`` and non-decreasing (SPEC §1.4; an
    equal step warns), with the values unchanged."""
    arr = np.array(d, dtype=float)
    ok = bool(np.all(np.isfinite(arr)) and arr[0] == 0 and np.all(np.diff(arr) >= 0))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        if ok:
            assert np.array_equal(check_deltas(arr, 3, "t"), arr)
        else:
            with pytest.raises(BalustradeError, match="deltas"):
                check_deltas(arr, 3, "t")


@settings(max_examples=60, deadline=None)
@given(tol=_ANY, iters=_ANY)
def test_check_stall_stop(tol, iters):
    """``(tol_acceptable, acceptable_iter)``: a finite real ``tol > 0`` and an int
    ``iters >= 1`` (no bools), else refused naming ``stall_stop``."""
    ok = (isinstance(tol, int | float) and not isinstance(tol, bool) and bool(np.isfinite(tol))
          and tol > 0 and isinstance(iters, int) and not isinstance(iters, bool) and iters >= 1)
    if ok:
        assert check_stall_stop((tol, iters)) == (float(tol), int(iters))
    else:
        with pytest.raises(BalustradeError, match="stall_stop"):
            check_stall_stop((tol, iters))
