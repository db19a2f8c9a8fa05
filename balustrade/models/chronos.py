"""The Chronos 1:28 race car (thesis §8.4, SPEC §2.33): dynamic bicycle (8.3) with the
drivetrain (8.4) and simplified Pacejka lateral tyre forces, Table 8.1 parameters.

State (Cartesian) ``[p_x, p_y, ψ, v_x, v_y, ω]``, input ``u = [T, δ]``:

* ``ṗ_x = v_x cos ψ − v_y sin ψ``, ``ṗ_y = v_x sin ψ + v_y cos ψ``, ``ψ̇ = ω``;
* ``v̇_x = (F_x − F_f sin δ + m v_y ω)/m``, ``v̇_y = (F_r + F_f cos δ − m v_x ω)/m``,
  ``ω̇ = (F_f l_f cos δ − F_r l_r)/I_z``;
* ``F_x = (c_1 − c_2 v_x) T − c_3 v_x² − c_4 v_x − c_5`` (8.4), ``c_5`` only when ``v_x > 0``;
* ``F_f = D_f sin(C_f atan(B_f α_f))``, ``F_r = D_r sin(C_r atan(B_r α_r))`` with the
  standard slip-angle convention of the SPEC §2.33 [Default] (the printed signs push along
  the slip): ``α_f = δ − atan((v_y + ω l_f)/v̄_x)``, ``α_r = atan((ω l_r − v_y)/v̄_x)``,
  ``v̄_x = max(v_x, 0.1)`` (numerical guard). Sanity: ``δ > 0``, ``v_y = ω = 0`` ⇒ ``ω̇ > 0``.

Frenet form (8.5) on a :class:`~balustrade.models.track.Track` with curvature ``κ(s)``:
state ``[s, e, μ, v_x, v_y, ω]``, ``ṡ = (v_x cos μ − v_y sin μ)/(1 − eκ(s))``,
``ė = v_x sin μ + v_y cos μ``, ``μ̇ = ω − κ(s) ṡ`` (``e`` positive to the left).

Discretization, 50 Hz (``T_s = 0.02`` s): the PCBF model is explicit Euler with one step
(the thesis' choice, :func:`chronos_frenet`); the simulated plant (:func:`chronos_plant`)
is classic RK4 with 10 sub-steps of 2 ms (Euler at 20 ms is only marginally stable for the
lateral tyre dynamics at ``v_x ≈ 1`` m/s: eigenvalue ≈ −97 1/s).

Constraints: front corners (8.6) ``e_lf = e + l_f sin μ + (w_veh/2) cos μ``,
``e_rf = e + l_f sin μ − (w_veh/2) cos μ`` with ``|e_lf|, |e_rf| <= w_track/2`` (SPEC
[Default]: half the width about the centre line), ``|μ| <= π/2``, ``0 <= T <= 1``,
``|δ| <= 0.4`` (:func:`chronos_sets`).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import casadi as ca
import numpy as np

from balustrade._checks import as_count, as_scalar
from balustrade.dsl.sets import Box
from balustrade.dsl.sets_function import FunctionSet
from balustrade.dsl.system import System
from balustrade.errors import BalustradeError
from balustrade.models.track import Track, oval

TS = 0.02
#: guard on ``v_x`` in the slip angles (SPEC §2.33 [Default] numerics)
VX_MIN = 0.1
T_MAX, DELTA_MAX = 1.0, 0.4
#: Cartesian and Frenet state names
CARTESIAN = ("p_x", "p_y", "psi", "v_x", "v_y", "omega")
FRENET = ("s", "e", "mu", "v_x", "v_y", "omega")


@dataclass(frozen=True)
class ChronosParams:
    """Table 8.1 (SI units)."""

    m: float = 0.187
    I_z: float = 0.003
    l_f: float = 0.046
    l_r: float = 0.052
    c1: float = 0.980
    c2: float = 0.003
    c3: float = 0.121
    c4: float = 0.017
    c5: float = 0.017
    B_f: float = 5.200
    C_f: float = 1.450
    D_f: float = 0.688
    B_r: float = 8.500
    C_r: float = 1.540
    D_r: float = 0.997
    w_veh: float = 0.072
    w_track: float = 0.5

    def __post_init__(self) -> None:
        for k, v in asdict(self).items():
            as_scalar(v, f"ChronosParams: {k}", low=0.0, low_open=k not in ("c2", "c4", "c5"))


#: the Table 8.1 parameters (frozen; the default of every function here)
TABLE_8_1 = ChronosParams()


def tyre_forces(vx: object, vy: object, omega: object, delta: object,
                p: ChronosParams = TABLE_8_1) -> tuple[object, object]:
    """``(F_f, F_r)``: simplified Pacejka with the standard slip angles (module docstring)."""
    vbar = ca.fmax(vx, VX_MIN)
    alpha_f = delta - ca.atan((vy + omega * p.l_f) / vbar)
    alpha_r = ca.atan((omega * p.l_r - vy) / vbar)
    F_f = p.D_f * ca.sin(p.C_f * ca.atan(p.B_f * alpha_f))
    F_r = p.D_r * ca.sin(p.C_r * ca.atan(p.B_r * alpha_r))
    return F_f, F_r


def drive_force(vx: object, T: object, p: ChronosParams = TABLE_8_1) -> object:
    """(8.4) ``F_x = (c_1 − c_2 v_x) T − c_3 v_x² − c_4 v_x − c_5``, ``c_5`` only for
    ``v_x > 0`` (SPEC §2.33 [Default])."""
    return (p.c1 - p.c2 * vx) * T - p.c3 * vx ** 2 - p.c4 * vx - ca.if_else(vx > 0, p.c5, 0.0)


def velocity_dynamics(vx: object, vy: object, omega: object, T: object, delta: object,
                      p: ChronosParams = TABLE_8_1) -> tuple[object, object, object]:
    """``(v̇_x, v̇_y, ω̇)`` of (8.3)."""
    F_f, F_r = tyre_forces(vx, vy, omega, delta, p)
    F_x = drive_force(vx, T, p)
    dvx = (F_x - F_f * ca.sin(delta) + p.m * vy * omega) / p.m
    dvy = (F_r + F_f * ca.cos(delta) - p.m * vx * omega) / p.m
    domega = (F_f * p.l_f * ca.cos(delta) - F_r * p.l_r) / p.I_z
    return dvx, dvy, domega


def cartesian_ode(p: ChronosParams = TABLE_8_1):
    """``ẋ = f(x, u)`` of (8.3) on the Cartesian state (callable on CasADi symbols)."""
    def f(x: ca.SX, u: ca.SX) -> ca.SX:
        psi, vx, vy, om = x[2], x[3], x[4], x[5]
        dvx, dvy, dom = velocity_dynamics(vx, vy, om, u[0], u[1], p)
        return ca.vertcat(vx * ca.cos(psi) - vy * ca.sin(psi),
                          vx * ca.sin(psi) + vy * ca.cos(psi), om, dvx, dvy, dom)
    return f


def frenet_ode(track: Track, p: ChronosParams = TABLE_8_1):
    """``ẋ = f(x, u)`` of (8.5) + (8.3) on the Frenet state ``[s, e, μ, v_x, v_y, ω]``."""
    def f(x: ca.SX, u: ca.SX) -> ca.SX:
        s, e, mu, vx, vy, om = (x[i] for i in range(6))
        kappa = track.kappa(s)
        ds = (vx * ca.cos(mu) - vy * ca.sin(mu)) / (1 - e * kappa)
        dvx, dvy, dom = velocity_dynamics(vx, vy, om, u[0], u[1], p)
        return ca.vertcat(ds, vx * ca.sin(mu) + vy * ca.cos(mu), om - kappa * ds,
                          dvx, dvy, dom)
    return f


def lateral_ode(kappa: float, p: ChronosParams = TABLE_8_1):
    """The progress-independent dynamics at a fixed curvature ``κ`` (the terminal-CBF design
    model of §8.4): (8.5) + (8.3) without ``s``, state ``[e, μ, v_x, v_y, ω]``, input
    ``[T, δ]``."""
    kappa = as_scalar(kappa, "lateral_ode: kappa")

    def f(x: ca.SX, u: ca.SX) -> ca.SX:
        e, mu, vx, vy, om = (x[i] for i in range(5))
        ds = (vx * ca.cos(mu) - vy * ca.sin(mu)) / (1 - e * kappa)
        dvx, dvy, dom = velocity_dynamics(vx, vy, om, u[0], u[1], p)
        return ca.vertcat(vx * ca.sin(mu) + vy * ca.cos(mu), om - kappa * ds, dvx, dvy, dom)
    return f


def _discrete(f_ct, nx: int, ts: float, method: str, steps: int, name: str) -> System:
    steps = as_count(steps, f"{name}: steps", low=1)
    return System.from_continuous(f_ct, nx=nx, nu=2, dt=ts, method=method, steps=steps,
                                  name=name)


def chronos_cartesian(ts: float = TS, method: str = "rk4", steps: int = 10,
                      params: ChronosParams = TABLE_8_1) -> System:
    """(8.3) in Cartesian coordinates, discretized at ``ts`` (default RK4, 10 sub-steps)."""
    return _discrete(cartesian_ode(params), 6, ts, method, steps, "chronos_cartesian")


def chronos_frenet(track: Track | None = None, ts: float = TS, method: str = "euler",
                   steps: int = 1, params: ChronosParams = TABLE_8_1) -> System:
    """(8.5) + (8.3) on ``track`` (default :func:`~balustrade.models.track.oval`),
    discretized at ``ts``; the default (explicit Euler, one step of 20 ms) is the PCBF
    model of §8.4."""
    track = oval() if track is None else track
    if not isinstance(track, Track):
        raise BalustradeError(f"chronos_frenet: track must be a Track, got "
                              f"{type(track).__name__}")
    return _discrete(frenet_ode(track, params), 6, ts, method, steps, "chronos_frenet")


def chronos_plant(track: Track | None = None, params: ChronosParams = TABLE_8_1
                  ) -> System:
    """The simulated car in Frenet coordinates: RK4, 10 sub-steps of 2 ms per 20 ms step."""
    return chronos_frenet(track, method="rk4", steps=10, params=params)


def corner_offsets(x: object, p: ChronosParams = TABLE_8_1) -> tuple[object, object]:
    """(8.6) ``(e_lf, e_rf)`` of a Frenet state (CasADi symbol or ``(..., 6)`` array)."""
    if isinstance(x, (ca.SX, ca.MX, ca.DM)):
        e, mu, sin, cos = x[1], x[2], ca.sin, ca.cos
    else:
        x = np.asarray(x, dtype=float)
        e, mu, sin, cos = x[..., 1], x[..., 2], np.sin, np.cos
    lf = e + p.l_f * sin(mu) + 0.5 * p.w_veh * cos(mu)
    rf = e + p.l_f * sin(mu) - 0.5 * p.w_veh * cos(mu)
    return lf, rf


def constraint_values(x: object, p: ChronosParams = TABLE_8_1) -> object:
    """``c_x(x)`` of §2.33 on Frenet states (``<= 0`` inside): ``e_lf − w/2``,
    ``−e_lf − w/2``, ``e_rf − w/2``, ``−e_rf − w/2``, ``μ − π/2``, ``−μ − π/2``
    (``w = w_track``)."""
    lf, rf = corner_offsets(x, p)
    half = 0.5 * p.w_track
    if isinstance(x, (ca.SX, ca.MX, ca.DM)):
        mu = x[2]
        return ca.vertcat(lf - half, -lf - half, rf - half, -rf - half,
                          mu - np.pi / 2, -mu - np.pi / 2)
    mu = np.asarray(x, dtype=float)[..., 2]
    return np.stack([lf - half, -lf - half, rf - half, -rf - half,
                     mu - np.pi / 2, -mu - np.pi / 2], axis=-1)


def chronos_sets(params: ChronosParams = TABLE_8_1) -> tuple[FunctionSet, Box]:
    """``X`` (the nonlinear corner and heading constraints, a
    :class:`~balustrade.dsl.sets_function.FunctionSet` on the Frenet state) and
    ``U = {0 <= T <= 1, |δ| <= 0.4}``."""
    X = FunctionSet(lambda x: constraint_values(x, params), 6, name="X_chronos")
    U = Box([0.0, -DELTA_MAX], [T_MAX, DELTA_MAX], name="U_chronos")
    return X, U


def steady_speed(T: float, p: ChronosParams = TABLE_8_1) -> float:
    """The straight-line speed with ``F_x = 0`` for drive command ``T``."""
    T = as_scalar(T, "steady_speed: T", low=0.0, high=1.0)
    a, b, c = p.c3, p.c4 + p.c2 * T, p.c5 - p.c1 * T
    disc = b * b - 4 * a * c
    return max(0.0, float((-b + np.sqrt(disc)) / (2 * a))) if disc >= 0 else 0.0


__all__ = ["CARTESIAN", "FRENET", "TABLE_8_1", "TS", "ChronosParams", "cartesian_ode",
           "chronos_cartesian", "chronos_frenet",
           "chronos_plant", "chronos_sets", "constraint_values", "corner_offsets",
           "drive_force", "frenet_ode", "lateral_ode", "steady_speed", "tyre_forces",
           "velocity_dynamics"]
