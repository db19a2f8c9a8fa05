"""The terminal policy ``π_f`` of the candidate (5.17)/(6.14) in the emitted C of Algorithms
5.2/6.4 (session 13, issues #14/#16): the C evaluates ``π_f``'s CasADi expression, so a
numpy-only ``π_f`` is refused by the emitters (it used to be replaced by an affine map
identified from a few calls, which the C applied where ``π_f`` is not that map), and an
explicit law (:class:`~balustrade.dsl.policies.AffinePolicy`, a ``casadi.Function``) gives
the C the expression Python evaluates."""

from __future__ import annotations

import warnings

import casadi as ca
import numpy as np
import pytest

from balustrade.codegen import emit_multiobjective, emit_robust
from balustrade.codegen.emit_robust import EMITTABLE_TARGET, _cand
from balustrade.control.multiobjective import MultiobjectivePCBFController
from balustrade.control.robust import RobustPCBFSafetyFilter
from balustrade.control.tube_functions import policy_expr
from balustrade.design.rpi import ellipsoidal_rpi
from balustrade.design.terminal_cbf import synthesize_terminal_cbf
from balustrade.dsl import AffinePolicy
from balustrade.errors import CodegenError, DegenerateResultWarning, ShapeError
from balustrade.models.unstable2d import unstable2d, unstable2d_setup

N = 5


@pytest.fixture(scope="module")
def tube() -> dict:
    system, s = unstable2d(), unstable2d_setup(N)
    error = ellipsoidal_rpi(system.A, system.B, s.W, s.X, s.U)
    X_E, U_E = error.tighten_state(s.X), error.tighten_input(s.U)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DegenerateResultWarning)
        cbf = synthesize_terminal_cbf(system.A, system.B, X_E, U_E, delta_N=s.deltas()[-1])
    return {"system": system, "s": s, "error": error, "cbf": cbf}


def _saturating(K: np.ndarray, limit: float):
    """``clip(K x, ±limit)``: numpy only; affine wherever ``|K x| <= limit``."""
    def pi_f(x: np.ndarray) -> np.ndarray:
        return np.clip(K @ np.asarray(x, dtype=float).reshape(-1), -limit, limit)
    return pi_f


def _robust(t: dict, pi_f) -> RobustPCBFSafetyFilter:
    s = t["s"]
    return RobustPCBFSafetyFilter.build(t["system"], s.X, s.U, t["cbf"], pi_f, N, s.deltas(),
                                        t["error"], s.alpha_f, slack_norm=1,
                                        target=EMITTABLE_TARGET, slack_target=EMITTABLE_TARGET)


def test_affine_policy_numbers_and_symbols_agree():
    K, k, x_s = np.array([[1.0, -2.0], [0.5, 3.0]]), np.array([0.1, -0.2]), np.array([1., 2.])
    pol = AffinePolicy(K, k, x_s)
    x = np.array([0.3, -0.7])
    np.testing.assert_array_equal(pol(x), K @ (x - x_s) + k)
    z = ca.SX.sym("z", 2)
    fn = ca.Function("p", [z], [pol(z)])
    np.testing.assert_allclose(np.asarray(fn(x)).reshape(-1), pol(x), rtol=1e-15)
    # no offset: exactly K x, on numbers and symbols
    lin = AffinePolicy(K)
    np.testing.assert_array_equal(lin(x), K @ x)
    assert str(lin(z)) == str(ca.mtimes(ca.DM(K), z))
    with pytest.raises(ShapeError, match="AffinePolicy: k"):
        AffinePolicy(K, np.zeros(3))
    with pytest.raises(ShapeError, match="AffinePolicy: x_s"):
        AffinePolicy(K, x_s=np.zeros(5))


def test_saturating_numpy_pi_f_is_refused_by_both_emitters(tube, tmp_path):
    """A numpy ``clip(K x, ±limit)`` passes the affine probe of the Python tube functions
    (it is ``K x`` at the probe points) but not beyond: the emitters refuse it, naming
    ``pi_f`` and how to pass it, instead of emitting the probed map (the old code emitted
    it; Python keeps the probed map with its check at every ``z_N``)."""
    K = np.asarray(tube["cbf"].K, dtype=float)
    limit = 100.0 * float(np.abs(K).sum())  # above |K x| at every probe (|x| < 10)
    pi_f = _saturating(K, limit)
    ctrl = _robust(tube, pi_f)
    assert ctrl._tube is not None and ctrl._tube.policy_check is not None
    # the map the probe identifies is K x: beyond the saturation it is not pi_f
    zN = ca.SX.sym("zN", 2)
    fitted = ca.Function("fit", [zN], [policy_expr(2, 1, pi_f, zN)])
    k = K.reshape(-1)
    far = 3.0 * limit * k / float(k @ k)
    np.testing.assert_allclose(float(fitted(far)), 3.0 * limit, rtol=1e-9)
    assert float(pi_f(far)[0]) == limit
    with pytest.raises(CodegenError, match=r"pi_f .*does not accept CasADi symbols.*"
                                           r"AffinePolicy\(K, k, x_s\)"):
        emit_robust(ctrl, "sat", tmp_path / "r")
    s = tube["s"]
    mo = MultiobjectivePCBFController.build(
        tube["system"], s.X, s.U, tube["cbf"], pi_f, N, s.deltas(), tube["error"], s.alpha_f,
        target=EMITTABLE_TARGET, slack_target=EMITTABLE_TARGET)
    with pytest.raises(CodegenError, match="pi_f"):
        emit_multiobjective(mo, "satmo", tmp_path / "m")
    # the same K x, given numpy-only (a plain function), is refused too: the C has no
    # expression of it to generate
    K = np.asarray(tube["cbf"].K, dtype=float)

    def numpy_kx(x):
        return K @ np.asarray(x, dtype=float).reshape(-1)

    with pytest.raises(CodegenError, match="numpy_kx"):
        emit_robust(_robust(tube, numpy_kx), "np", tmp_path / "n")
    # while the terminal CBF's own policy is an explicit affine law and emits
    assert isinstance(tube["cbf"].policy, AffinePolicy)
    emit_robust(_robust(tube, tube["cbf"].policy), "cbfpol", tmp_path / "c")


@pytest.mark.parametrize("kind", ["affine", "function", "matrix", "pair"])
def test_explicit_pi_f_gives_the_c_the_python_candidate(tube, kind):
    """An :class:`AffinePolicy`, a ``casadi.Function``, a matrix ``K`` or a pair ``(K, k)``
    ``π_f`` (the last two become an ``AffinePolicy``, session 15): the candidate function the
    C is generated from (``_cand``) is the one the Python controller evaluates, value for
    value, where ``K z_N`` is large (where a saturating numpy policy would differ)."""
    K = np.asarray(tube["cbf"].K, dtype=float)
    if kind == "matrix":
        pi_f = K
    elif kind == "pair":
        pi_f = (K, np.zeros(1))
    elif kind == "affine":
        pi_f = AffinePolicy(K)
    else:
        z = ca.SX.sym("x", 2)
        pi_f = ca.Function("pi_f", [z], [ca.mtimes(ca.DM(K), z)])
    ctrl = _robust(tube, pi_f)
    assert ctrl._tube is not None and ctrl._tube.policy_check is None
    c_fn = _cand("c_cand", ctrl.deployment_spec())
    rng = np.random.default_rng(0)
    for _ in range(5):
        z = rng.uniform(-3, 3, (2, N + 1))
        v, xi = rng.uniform(-1, 1, (1, N)), rng.uniform(0, 1, (ctrl.X_E.H.shape[0], N))
        a, b = c_fn(z, v, xi), ctrl._tube.cand_fn(z, v, xi)
        for x, y in zip(a, b):
            np.testing.assert_array_equal(np.asarray(x), np.asarray(y))


def test_affine_policy_of_the_wrong_size_is_refused_naming_pi_f(tube, tmp_path):
    """An :class:`AffinePolicy` for 3 states on the 2-state system: refused when the
    controller is built (session 15; the emitter used to find it), naming ``pi_f`` and the
    shape it needs."""
    with pytest.raises(ShapeError, match=r"pi_f \(AffinePolicy K\).*\(1, 2\)"):
        _robust(tube, AffinePolicy(np.ones((1, 3))))


def test_pi_f_as_a_matrix_or_pair_is_the_affine_law_and_bad_forms_are_refused(tube):
    """``pi_f = (K, k)`` is ``K x + k`` (independent: the matrix product) in both
    controllers of the candidate (5.17)/(6.14), and in the emitted step (the same
    expression, previous test); a tuple of another length, a matrix of the wrong shape or
    a non-callable are refused when the controller is built, naming ``pi_f`` and the
    accepted forms."""
    from balustrade.errors import BalustradeError

    K = np.asarray(tube["cbf"].K, dtype=float)
    k = np.array([0.25])
    s = tube["s"]
    mo = MultiobjectivePCBFController.build(
        tube["system"], s.X, s.U, tube["cbf"], (K, k), N, s.deltas(), tube["error"],
        s.alpha_f, target=EMITTABLE_TARGET, slack_target=EMITTABLE_TARGET)
    for ctrl in (_robust(tube, (K, k)), mo):
        assert isinstance(ctrl.pi_f, AffinePolicy) and ctrl._tube.policy_check is None
        for x in np.random.default_rng(1).uniform(-3, 3, (4, 2)):
            np.testing.assert_allclose(ctrl.pi_f(x), K @ x + k, rtol=0, atol=1e-15)
    for bad, match in (((K,), r"pi_f as a tuple must be the pair \(K, k\).*1 entries"),
                       ((K, k, k), r"pi_f as a tuple.*3 entries"),
                       (np.ones((2, 2)), r"pi_f \(the matrix K\)"),
                       ((K, np.ones(2)), r"pi_f k"),
                       (3.0, r"pi_f must be a matrix K .*got float")):
        with pytest.raises(BalustradeError, match=match):
            _robust(tube, bad)
