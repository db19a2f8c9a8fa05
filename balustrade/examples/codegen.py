"""Ready-made emittable targets (used by ``balustrade codegen NAME``, tests and benchmarks).

* ``pendulum_pcbf`` — the PCBF pair (2.24)+(2.23) of the pendulum (7.10) with the terminal
  CBF of (7.11), its dynamics, a ``main.c`` closed loop (``u_p = 2``) and a ``Makefile``;
* ``pendulum_approximate`` — Algorithm 7.5 ((7.6) then (7.5), certification shortcut) with
  ``ĥ = h_f`` of (7.11) standing in for a learned surrogate (a network exported to CasADi
  by :mod:`balustrade.learn` is emitted the same way);
* ``pendulum_functions`` — plain functions: dynamics, its Jacobians, ``h_f`` and its
  gradient.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import casadi as ca
import numpy as np

from balustrade.codegen.emit import Emitted, emit_functions, emit_pcbf, write_example

#: initial states of the closed-loop example (inside and near the boundary of X)
PENDULUM_X0 = np.array([[0.3, 0.5], [-0.4, 1.0], [0.45, -1.2], [0.0, 0.0]])
PENDULUM_U_P = 2.0


def pendulum_pcbf_filter() -> object:
    """The pendulum PCBF safety filter of Section 7.5 on the ``fast-sqp`` target."""
    from balustrade.control.pcbf import PCBFSafetyFilter
    from balustrade.examples.pendulum import pendulum_terminal_cbf
    from balustrade.models.pendulum import pendulum, pendulum_setup

    system, s = pendulum(), pendulum_setup()
    h_f = pendulum_terminal_cbf()
    return PCBFSafetyFilter.build(system, s.X, s.U, h_f, s.N, s.deltas, s.alpha_f,
                                  slack_norm=1, target="fast-sqp")


def pendulum_functions() -> dict[str, ca.Function]:
    """Plain functions of the pendulum example: ``f``, ``∂f/∂x``, ``∂f/∂u``, ``h_f``, ``∇h_f``."""
    from balustrade.examples.pendulum import pendulum_terminal_cbf
    from balustrade.models.pendulum import pendulum

    return language_functions(pendulum(), pendulum_terminal_cbf())


def language_functions(system: object, h_f: Callable | None = None,
                       value: Callable | None = None) -> dict[str, ca.Function]:
    """The plain functions of a formulation worth emitting: the dynamics ``f(x, u)`` and
    its Jacobians, and for each of ``h_f`` (terminal CBF) and ``value`` (a value-function
    surrogate such as ``ĥ_PB`` of (7.5)) the function and its gradient."""
    x, u = ca.SX.sym("x", system.nx), ca.SX.sym("u", system.nu)
    zeros_w, zeros_t = ca.DM.zeros(system.nw), ca.DM.zeros(system.ntheta)
    xn = system.function(x, u, zeros_w, zeros_t)
    out = {"dynamics": ca.Function("dynamics", [x, u], [xn], ["x", "u"], ["x_next"]),
           "dynamics_jac": ca.Function("dynamics_jac", [x, u],
                                       [ca.jacobian(xn, x), ca.jacobian(xn, u)],
                                       ["x", "u"], ["A", "B"])}
    for key, fn in (("h_f", h_f), ("value", value)):
        if fn is None:
            continue
        v = ca.SX(fn(x))
        out[key] = ca.Function(key, [x], [v], ["x"], ["h"])
        out[f"{key}_grad"] = ca.Function(f"{key}_grad", [x], [ca.gradient(v, x)], ["x"],
                                         ["grad"])
    return out


def emit_pendulum_pcbf(out_dir: str | Path, name: str = "pendulum_pcbf",
                       steps: int = 30) -> Emitted:
    """Emit the pendulum PCBF step, its dynamics, ``main.c`` and the ``Makefile``."""
    from balustrade.models.pendulum import pendulum

    ctrl = pendulum_pcbf_filter()
    emitted = emit_pcbf(ctrl, name, out_dir, dynamics=pendulum().function)
    write_example(emitted, PENDULUM_X0, PENDULUM_U_P, steps)
    return emitted


def pendulum_approximate_filter(h_hat: Callable | None = None) -> object:
    """Algorithm 7.5 for the pendulum on the ``fast-sqp`` target; ``ĥ`` defaults to the terminal CBF
    ``h_f`` of (7.11) (replace it by a trained surrogate)."""
    from balustrade.control.approximate import ApproximatePCBFFilter
    from balustrade.examples.pendulum import pendulum_terminal_cbf
    from balustrade.models.pendulum import pendulum, pendulum_setup

    h_hat = pendulum_terminal_cbf() if h_hat is None else h_hat
    return ApproximatePCBFFilter(pendulum(), pendulum_setup().U, h_hat, target="fast-sqp")


def emit_pendulum_approximate(out_dir: str | Path,
                              name: str = "pendulum_approximate") -> Emitted:
    """Emit Algorithm 7.5 for the pendulum (with its dynamics)."""
    from balustrade.codegen.emit import emit_approximate
    from balustrade.models.pendulum import pendulum

    return emit_approximate(pendulum_approximate_filter(), name, out_dir,
                            dynamics=pendulum().function)


def emit_pendulum_functions(out_dir: str | Path, name: str = "pendulum_functions") -> Emitted:
    """Emit the plain functions of the pendulum example."""
    return emit_functions(pendulum_functions(), name, out_dir)


TARGETS: dict[str, Callable[..., Emitted]] = {
    "pendulum_pcbf": emit_pendulum_pcbf,
    "pendulum_functions": emit_pendulum_functions,
    "pendulum_approximate": emit_pendulum_approximate,
}
