"""Online terminal-set enlargement for Algorithm 4.1 (thesis Theorem 4.12, Remark 4.13,
SPEC §2.22): after every successful solve of (4.5) its tube pairs ``(z*_i, α*_i)`` (and the
zero-dilation points of Remark 4.13) join the generators of the terminal set.

Bookkeeping per recorded solution:

1. candidates: the ``N + 1`` pairs and, with ``zero_dilation`` and the vertices of ``𝕏₀``,
   the ``(N + 1)·n₀`` zero-dilation points;
2. candidates inside the current hull (generators and base set) are dropped — one warm-started
   separation LP each (:func:`balustrade.backends.hull.hull_distances`);
3. when more than ``capacity`` generators would result, the union is pruned to its extreme
   points (:func:`balustrade.backends.hull.extreme_points`); if that is still more than
   ``capacity``, the solution's candidates are *not* added (counted in ``rejected``). Keeping
   only some of them could drop the successor pair of a kept one and break Assumption 4.11;
   the old set stays valid for every later (nested) ``Θ``.

``capacity`` bounds the generator count so that the compiled (4.5) keeps one shape
(:meth:`TerminalSet.slot`, padding with ``(0, 0)``). Call :meth:`reset` whenever ``Θ`` goes back
to a larger set: the recorded tubes are robust only for the sets they were solved with.
"""

from __future__ import annotations

import numpy as np

from balustrade.backends.hull import extreme_points, hull_distances
from balustrade.errors import BalustradeError
from balustrade.problems.rapsf import TerminalSet
from balustrade.problems.rapsf_enlarge import base_generators, tube_pairs, zero_dilation_points

#: ``zero_dilation=None`` adds Remark 4.13's points only when ``𝕏₀`` has at most this many
#: vertices per state dimension: each tube gives ``(N + 1)·n₀`` candidates, and for the
#: 3-mass chain (``n₀ = 216`` in 6 dimensions) their pruning took ~85 s per solve (measured
#: under load) with the capacity exceeded by the first tube alone.
ZERO_DILATION_MAX_VERTICES = 4


class TerminalEnlargement:
    """The growing generator list of the enlarged terminal set (4.10) for a state of
    dimension ``n`` over the base set ``base`` (``None``: the §4.7 default). ``X0_vertices``
    (rows) enable the zero-dilation points of Remark 4.13 (``zero_dilation``: ``None`` =
    when ``n₀ <= 4n``, see :data:`ZERO_DILATION_MAX_VERTICES`); ``capacity`` bounds the
    generator count; ``tol`` is the hull-distance tolerance of the pruning."""

    def __init__(self, n: int, base: TerminalSet | None = None,
                 X0_vertices: np.ndarray | None = None, capacity: int = 64,
                 zero_dilation: bool | None = None, tol: float = 1e-7):
        if base is not None and base.has_generators:
            raise BalustradeError("TerminalEnlargement: base must be an H-representation or "
                                  "the default terminal set, not a hull of generators")
        if int(capacity) < 1:
            raise BalustradeError(f"TerminalEnlargement: capacity must be positive, got "
                                  f"{capacity}")
        self.n, self.base, self.capacity, self.tol = int(n), base, int(capacity), float(tol)
        self.X0_vertices = None if X0_vertices is None else np.atleast_2d(
            np.asarray(X0_vertices, dtype=float))
        if zero_dilation is None:                   # auto: only for few vertices of 𝕏₀
            zero_dilation = (self.X0_vertices is not None
                             and len(self.X0_vertices) <= ZERO_DILATION_MAX_VERTICES * self.n)
        self.zero_dilation = bool(zero_dilation) and self.X0_vertices is not None
        self._base = base_generators(base, self.n)
        self.reset()

    def reset(self) -> None:
        """No generators (the base set only)."""
        self.generators = np.zeros((self.n + 1, 0))
        self.tubes: list[tuple[np.ndarray, np.ndarray]] = []
        self.version = 0
        self.recorded = 0
        self.rejected = 0
        self.truncated = 0

    def candidates(self, z: np.ndarray, alpha: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The tube pairs of one solution and, if enabled, its zero-dilation points (columns),
        with the tube index ``i`` of each column."""
        P = tube_pairs(z, alpha, self.n)
        idx = np.arange(P.shape[1])
        if self.zero_dilation:
            P = np.hstack([P, zero_dilation_points(z, alpha, self.X0_vertices)])
            idx = np.concatenate([idx, np.repeat(idx, len(self.X0_vertices))])
        return P, idx

    def record(self, z: np.ndarray, alpha: np.ndarray) -> int:
        """Add the solution ``(z, α)`` of a successful solve; returns the net change of the
        generator count (0 when all candidates lie in the hull or none fit). The tube is kept
        in ``tubes`` either way (for an offline hull of all data,
        :func:`balustrade.design.rapsf_enlarge.enlarged_terminal_set`)."""
        C, idx = self.candidates(z, alpha)
        self.tubes.append((np.array(z, dtype=float), np.array(alpha, dtype=float).ravel()))
        self.recorded += 1
        ref = self._reference(self.generators)
        if ref.shape[1]:
            out = hull_distances(C, ref) > self.tol * (1.0 + np.abs(C).sum(axis=0))
            C, idx = C[:, out], idx[out]
        if C.shape[1] == 0:
            return 0
        new = self._merged(C)
        m = 0
        while new.shape[1] > self.capacity:
            # too many: keep only the tubes i >= m (a suffix keeps every successor pair)
            kept = self._extreme_count(new, C)
            m = _smallest_suffix(idx, kept, new.shape[1] - len(kept), self.capacity, m + 1)
            if m is None:
                self.rejected += 1
                return 0
            C, idx = C[:, idx >= m], idx[idx >= m]
            new = self._merged(C)
        if m > 0:
            self.truncated += 1
        added = new.shape[1] - self.generators.shape[1]
        self.generators = new
        self.version += 1
        return added

    def _merged(self, C: np.ndarray) -> np.ndarray:
        new = np.hstack([self.generators, C])
        if new.shape[1] > self.capacity:
            new = new[:, extreme_points(new, self.tol, fixed=self._base)]
        return new

    def _extreme_count(self, new: np.ndarray, C: np.ndarray) -> np.ndarray:
        """Which candidate columns of ``C`` survived in ``new`` (a boolean per column)."""
        if C.shape[1] == 0:
            return np.zeros(0, dtype=bool)
        return np.array([np.any(np.all(np.isclose(new, c[:, None], rtol=0, atol=1e-15),
                                       axis=0)) for c in C.T])

    def _reference(self, V: np.ndarray) -> np.ndarray:
        return V if self._base is None else np.hstack([V, self._base])

    @property
    def terminal_set(self) -> TerminalSet:
        """The current enlarged set (numeric generators over the base)."""
        return TerminalSet.from_generators(self.generators[:self.n], self.generators[self.n],
                                           self.base)

    def padded(self) -> np.ndarray:
        """The generators padded with ``(0, 0)`` to ``capacity`` columns (the value of the
        parameter ``terminal_generators`` of :meth:`TerminalSet.slot`)."""
        out = np.zeros((self.n + 1, self.capacity))
        out[:, :self.generators.shape[1]] = self.generators
        return out


def _smallest_suffix(idx: np.ndarray, kept: np.ndarray, n_old: int, capacity: int,
                     start: int) -> int | None:
    """The smallest ``m >= start`` whose surviving candidates of tubes ``i >= m`` fit next
    to the ``n_old`` surviving old generators, or ``None`` when that leaves no surviving
    candidate (nothing worth adding)."""
    for m in range(start, int(idx.max()) + 2 if idx.size else start + 1):
        count = int(np.count_nonzero(kept & (idx >= m)))
        if n_old + count <= capacity:
            return m if count else None     # no extreme candidate left: nothing to add
    return None


__all__ = ["ZERO_DILATION_MAX_VERTICES", "TerminalEnlargement"]
