"""Low-overhead calls of compiled CasADi problems from Python (hot loops of the filters).

:class:`Buffered` evaluates a CasADi Function through preallocated buffers; :class:`FastNLP`
is the first attempt of :meth:`CasadiCompiled.solve` without its Python bookkeeping. Both
keep the semantics of the compiled problem; callers fall back to ``compiled.solve`` (and its
retry chain) whenever :meth:`FastNLP.solve` returns ``None``.
"""

from __future__ import annotations

import casadi as ca
import numpy as np

from balustrade.backends.casadi_backend import CasadiCompiled
from balustrade.errors import BalustradeError

#: per plugin, the return status (``stats()["return_status"]``) of a stop at the solver's
#: acceptable level, which ``error_on_fail`` counts as converged and the backend reports
#: ``optimal_inaccurate`` (``casadi_backend._RETURN_STATUS``)
ACCEPTABLE_RETURN_STATUS: dict[str, str] = {"ipopt": "Solved_To_Acceptable_Level"}


class Buffered:
    """A CasADi Function evaluated through its ``FunctionBuffer``: inputs and outputs are
    preallocated float64 arrays bound once, so a call copies the arguments in place and
    runs the function — no numpy → ``DM`` conversion (≈ 20 µs per argument) and no output
    dictionary. Inputs must be dense. :attr:`res` is overwritten by the next call."""

    def __init__(self, fn: ca.Function):
        for i in range(fn.n_in()):
            if fn.nnz_in(i) != fn.numel_in(i):
                raise BalustradeError(f"Buffered: input {fn.name_in(i)!r} of {fn.name()!r} "
                                      "is sparse")
        self.function = fn
        self._buffer, self._eval = fn.buffer()
        self.args = [np.zeros(fn.nnz_in(i)) for i in range(fn.n_in())]
        self.res = [np.zeros(fn.nnz_out(i)) for i in range(fn.n_out())]
        for i, a in enumerate(self.args):
            self._buffer.set_arg(i, memoryview(a))
        for i, r in enumerate(self.res):
            self._buffer.set_res(i, memoryview(r))

    def stats(self) -> dict:
        """The solver statistics of the last call (an ``nlpsol``: ``return_status``, ...)."""
        return self._buffer.stats()

    def __call__(self, *args: object) -> list[np.ndarray]:
        for dst, src in zip(self.args, args):
            dst[:] = src
        self._eval()
        return self.res


class FastNLP:
    """The first attempt of :meth:`CasadiCompiled.solve` with less Python around it: the
    same NLP and options (plus ``error_on_fail``, so a failed solve raises instead of
    needing ``stats()``), evaluated through a :class:`Buffered` ``nlpsol`` from a primal
    start with zero multipliers (a cold start, as the emitted C does). :meth:`solve`
    returns ``None`` when the solver fails or stops at its acceptable level (IPOPT's
    ``Solved_To_Acceptable_Level``: ``optimal_inaccurate`` in the backend, not optimal);
    the caller then runs ``compiled.solve`` (with its retry chain), so results and
    fallbacks are those of the compiled problem."""

    def __init__(self, compiled: CasadiCompiled, check_stop: bool = True):
        self.compiled = compiled
        opts = {**compiled.options, **getattr(compiled, "derivatives", {}),
                "error_on_fail": True}
        self.nlp = Buffered(ca.nlpsol(f"{compiled.ocp.name}_fast", compiled.solver_name,
                                      compiled.nlp, opts))
        names = self.nlp.function.name_in()
        for name in ("lbx", "ubx", "lbg", "ubg"):
            self.nlp.args[names.index(name)][:] = getattr(compiled, name)
        self._x0 = self.nlp.args[names.index("x0")]
        self._p = self.nlp.args[names.index("p")]
        self._lam = [self.nlp.args[names.index(n)] for n in ("lam_x0", "lam_g0")]
        #: the solver's return status of a stop at its acceptable level, which the backend
        #: reports optimal_inaccurate (None: the solver has none)
        self._acceptable = ACCEPTABLE_RETURN_STATUS.get(compiled.solver_name)
        self._w0 = compiled.layout.initial()  # the user's init, then the epigraph blocks'
        self.offsets = compiled.layout.user().slices
        #: ``check_stop=False``: a caller that does not take the point as an optimum (the
        #: multi-start of (7.6) re-evaluates any point of U) skips the status read
        #: (≈ 80 µs per stats() call).
        self._check_stop = check_stop
        self.param_offsets = compiled.ocp.parameter_layout.slices

    def pack(self, **params: object) -> np.ndarray:
        """The parameter vector (as ``OCP.pack_parameters``; column-major) from values by
        name, written into the solver's own input buffer (parameters not given keep their
        previous values)."""
        for name, value in params.items():
            self._p[self.param_offsets[name]] = np.ravel(value, order="F")
        return self._p

    def solve(self, p: np.ndarray, start: dict[str, np.ndarray]
              ) -> tuple[np.ndarray, float] | None:
        """``(w, objective)`` of a successful solve with parameter vector ``p`` (as
        ``OCP.pack_parameters``) from the primal ``start`` (missing variables take their
        ``init``), else ``None``. ``w`` is the solver's output buffer (overwritten by the
        next solve): copy what you keep."""
        self._x0[:] = self._w0
        for name, value in start.items():  # column-major, as OCP.pack_variables
            self._x0[self.offsets[name]] = np.ravel(value, order="F")
        self._p[:] = p
        for lam in self._lam:
            lam[:] = 0.0
        try:
            self.nlp._eval()
        except RuntimeError:  # not converged (error_on_fail) or an evaluation error
            return None
        if self._check_stop and self._acceptable is not None and \
                self.nlp._buffer.stats().get("return_status") == self._acceptable:
            # error_on_fail lets IPOPT's acceptable stop through as converged; the
            # compiled problem reports it optimal_inaccurate (used, flagged), never optimal:
            # the caller's compiled.solve names it (session 14, C = Python statuses)
            return None
        return self.nlp.res[0], float(self.nlp.res[1][0])

