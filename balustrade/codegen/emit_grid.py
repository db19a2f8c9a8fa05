"""Emit Algorithm 8.7 (SPEC §2.34), the input-grid approximate PCBF filter, as C.

:func:`emit_grid` reads a :class:`~balustrade.control.approximate.GridPCBFFilter` through its
:class:`~balustrade.control.deploy.GridDeployment` and writes the module of
:func:`balustrade.codegen.emit.emit_approximate`'s layout: ``ĥ`` and ``ĥ(f(x, u))`` emitted
by CasADi as ``<name>_h``/``<name>_h_next``, the numbers of the step (offsets, box, scale,
``ρ``, ``u_init``) in ``<name>_config.h`` and the step itself, the static ``bal/grid.c``,
instantiated under the prefix ``<name>``. No solver is involved, so no library is linked.
"""

from __future__ import annotations

from pathlib import Path

import casadi as ca
import numpy as np

from balustrade.codegen import cfiles as C
from balustrade.codegen import status as S
from balustrade.codegen.emit import (
    Emitted,
    _check_dynamics,
    _check_identifier,
    _generate,
    _out_dir,
    _spec,
    _write_module,
)
from balustrade.control.deploy import GridDeployment
from balustrade.dsl.sets import Box
from balustrade.errors import CodegenError


def _check_numbers(name: str, spec: GridDeployment, nu: int
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(offsets (M, nu), scale (nu,), u_init (nu,))`` of a (possibly hand-built) spec, all
    finite, ``scale > 0`` and ``rho`` finite; else a CodegenError naming the field and its
    shape (the C arrays are sized by ``nu``)."""
    offsets = np.asarray(spec.offsets, dtype=float)
    if offsets.ndim not in (1, 2) or offsets.size == 0 or offsets.size % nu or \
            (offsets.ndim == 2 and offsets.shape[1] != nu):
        raise CodegenError(f"{name}: offsets must have shape (M, {nu}), got {offsets.shape}")
    scale = np.asarray(spec.scale, dtype=float)
    u_init = np.asarray(spec.u_init, dtype=float)
    if scale.size != nu or u_init.size != nu:
        raise CodegenError(f"{name}: scale and u_init must have {nu} entries, got shapes "
                           f"{scale.shape} and {u_init.shape}")
    if not (np.all(np.isfinite(offsets)) and np.all(np.isfinite(scale)) and
            np.all(scale > 0) and np.isfinite(float(spec.rho))):
        raise CodegenError(f"{name}: offsets, scale and rho must be finite and scale > 0")
    return offsets.reshape(-1, nu), scale.reshape(-1), u_init.reshape(-1)


def emit_grid(controller: object, name: str, out_dir: str | Path,
              dynamics: ca.Function | None = None) -> Emitted:
    """Emit Algorithm 8.7 of a :class:`~balustrade.control.approximate.GridPCBFFilter` (or
    its :class:`~balustrade.control.deploy.GridDeployment`) as one C call per control step:
    ``<name>_step(x, u_p, u_out, h_out, status, work)`` evaluates ``ĥ(f(x, u_i))`` on all
    rate-limited candidates ``u_i`` around ``u_{k−1}`` in one loop and applies the
    admissible one (``ĥ(f(x, u_i)) <= ρ ĥ(x)``) closest to ``u_p``, with the candidate
    order, tie-breaking, fallbacks and status words of the Python filter (``bal/grid.h``).
    ``U`` must be a :class:`~balustrade.dsl.sets.Box` (candidates are clipped to it).
    ``dynamics`` (e.g. ``system.function``) is emitted too, as ``<name>_dynamics``."""
    _check_identifier(name)
    _check_dynamics(name, dynamics)
    spec = _spec(controller, name, GridDeployment, "GridPCBFFilter")
    if not isinstance(spec.U, Box):
        raise CodegenError(f"{name}: the C grid step clips its candidates to U, so U must be "
                           f"a Box, got {type(spec.U).__name__}")
    system = spec.system
    nx, nu = system.nx, system.nu
    offsets, scale, u_init = _check_numbers(name, spec, nu)
    x, u = ca.SX.sym("x", nx), ca.SX.sym("u", nu)
    h = spec.h
    functions = {f"{name}_h": ca.Function(f"{name}_h", [x], [h(x)], ["x"], ["h"]),
                 f"{name}_h_next": ca.Function(f"{name}_h_next", [x, u], [h(system(x, u))],
                                               ["x", "u"], ["h_next"])}
    for fn in functions.values():
        if fn.numel_out(0) != 1:  # the C reads one double: more would overrun it
            raise CodegenError(f"{name}: ĥ must be scalar, {fn.name()} has an output of "
                               f"shape {fn.size_out(0)}")
    out_dir = _out_dir(out_dir, name)
    if dynamics is not None:
        functions[f"{name}_dynamics"] = dynamics
    files = _generate(functions, name, out_dir)
    cfg = C.Config()
    cfg.comment(f"---- Algorithm 8.7, the grid PCBF filter {name} (bal/grid.h) ----")
    cfg.define(f"{name}_NX", nx)
    cfg.define(f"{name}_NU", nu)
    cfg.define(f"{name}_M", len(offsets), "offsets around u_{k-1} (candidates at most)")
    cfg.define(f"{name}_RHO", C.c_double(spec.rho), "decrease h^(f(x, u)) <= rho h^(x)")
    cfg.array(f"{name}_U_LB", spec.U.lb)
    cfg.array(f"{name}_U_UB", spec.U.ub)
    cfg.comment("offsets j du, |j du| <= half width (rows, itertools.product order)")
    cfg.matrix(f"{name}_OFFSETS", offsets)
    cfg.array(f"{name}_SCALE", scale)
    cfg.array(f"{name}_U_INIT", u_init)
    cfg.status(S.GRID, "BAL_GRID_STATUS_CODES")
    manifest = {"kind": "grid", "nx": nx, "nu": nu, "n_offsets": len(offsets),
                "rho": float(spec.rho),
                "U": {"lb": list(map(float, spec.U.lb)), "ub": list(map(float, spec.U.ub))},
                "dynamics": dynamics is not None, "grid_status": S.manifest(S.GRID)}
    return _write_module(name, out_dir, "Algorithm 8.7, the grid PCBF filter", cfg,
                         [("grid", name)], files, manifest, ())
