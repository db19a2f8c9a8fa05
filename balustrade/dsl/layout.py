"""One stacked layout of named blocks: how decision variables and parameters of an
:class:`~balustrade.dsl.ocp.OCP` sit in the flat vectors ``w`` and ``p`` a solver sees.

A :class:`Layout` is an ordered tuple of :class:`Entry` (name, shape, slice), stacked
column-major in declaration order; it packs dicts of named values into a flat vector and
unpacks flat vectors into named arrays, with the shape and finiteness checks (and the error
messages) of the language. Lowering passes that add variables (the epigraph ``t`` of a norm
cost, :mod:`balustrade.backends.passes.epigraph`) :meth:`Layout.extend` it: the added blocks
come after the user's, carry their bounds and initial values, and are marked with the pass
that added them, so that the CasADi backend, its fast path and the C code generator ask the
layout where the user's variables end instead of passing ``n_user`` around.

A layout is also written to and read from the generated C's manifest (:meth:`Layout.to_dict`,
:meth:`Layout.from_dict`), so the C runtime packs parameters with the same checks.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import dataclass

import numpy as np

from balustrade._checks import as_float_array
from balustrade.errors import BalustradeError, NonFiniteError, ShapeError

#: the origin of blocks declared by the user (any other origin names the pass that added them)
USER = "user"
#: a parameter value at most ``LB_TOL·max(1, |lb|)`` below its lower bound is a rounding of
#: the bound (a solver's slack at -1e-17) and is packed as the bound; further below: refused
LB_TOL = 1e-9


@dataclass(frozen=True)
class Entry:
    """One named block of a stacked vector: ``vector[slice]`` reshaped column-major to
    ``shape``. ``lb``/``ub``/``init`` are flat (column-major); ``init`` is the value used
    when none is given (a parameter's declared value, ``None`` if it has none)."""

    name: str
    shape: tuple[int, int]
    slice: slice
    init: np.ndarray | None = None
    lb: np.ndarray | None = None
    ub: np.ndarray | None = None
    origin: str = USER

    @property
    def size(self) -> int:
        return self.shape[0] * self.shape[1]


class Layout:
    """Named blocks stacked column-major in order (:class:`Entry`).

    ``owner`` and ``noun`` word the error messages (``"pendulum: unknown parameters ..."``);
    ``value_label`` names a value given for an entry (``"parameter 'x0'"``, ``"initial guess
    'u'"``)."""

    def __init__(self, entries: Iterable[Entry] = (), owner: str = "", noun: str = "variable",
                 value_label: str | None = None):
        self.entries: tuple[Entry, ...] = tuple(entries)
        self.owner, self.noun = owner, noun
        self.value_label = noun if value_label is None else value_label
        self.by_name: dict[str, Entry] = {e.name: e for e in self.entries}
        if len(self.by_name) != len(self.entries):
            raise BalustradeError(f"{owner}: a layout cannot hold two blocks of one name")
        self.size = self.entries[-1].slice.stop if self.entries else 0
        #: size of the leading user blocks (those not added by a pass)
        self.user_size = sum(e.size for e in self.entries if e.origin == USER)
        self._user = [e for e in self.entries if e.origin == USER]

    @classmethod
    def stack(cls, items: Iterable[tuple[str, tuple[int, int], np.ndarray | None,
                                          np.ndarray | None, np.ndarray | None]],
              owner: str = "", noun: str = "variable", value_label: str | None = None
              ) -> Layout:
        """A layout from ``(name, shape, init, lb, ub)`` tuples (arrays of ``shape`` or
        ``None``), stacked in order."""
        entries, k = [], 0
        for name, shape, init, lb, ub in items:
            shape = (int(shape[0]), int(shape[1]))
            n = shape[0] * shape[1]
            entries.append(Entry(name, shape, slice(k, k + n), _flat(init), _flat(lb),
                                 _flat(ub)))
            k += n
        return cls(entries, owner, noun, value_label)

    # -- queries -----------------------------------------------------------------------
    def __len__(self) -> int:
        return len(self.entries)

    def __contains__(self, name: object) -> bool:
        return name in self.by_name

    def __getitem__(self, name: str) -> Entry:
        try:
            return self.by_name[name]
        except KeyError:
            raise BalustradeError(f"{self.owner}: no {self.noun} named {name!r}; declared: "
                                  f"{list(self.by_name)}") from None

    @property
    def names(self) -> list[str]:
        return list(self.by_name)

    @property
    def slices(self) -> dict[str, slice]:
        """``name -> slice`` of every block."""
        return {e.name: e.slice for e in self.entries}

    @property
    def added(self) -> tuple[Entry, ...]:
        """The blocks added by lowering passes (after the user's)."""
        return tuple(e for e in self.entries if e.origin != USER)

    def user(self) -> Layout:
        """The layout of the user's blocks only."""
        if not self.added:
            return self
        return Layout(self._user, self.owner, self.noun, self.value_label)

    def initial(self) -> np.ndarray:
        """The stacked initial values (zeros where an entry has none)."""
        return self._stacked("init", 0.0)

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """The stacked lower and upper bounds (``∓inf`` where an entry has none)."""
        return self._stacked("lb", -np.inf), self._stacked("ub", np.inf)

    def _stacked(self, field: str, fill: float) -> np.ndarray:
        chunks = [np.full(e.size, fill) if getattr(e, field) is None else getattr(e, field)
                  for e in self.entries]
        return np.concatenate(chunks) if chunks else np.zeros(0)

    # -- pack / unpack -----------------------------------------------------------------
    def pack(self, values: Mapping[str, object] | None) -> np.ndarray:
        """Stack named values (checked for shape and finiteness) in order; an entry not
        given takes its ``init`` (a variable's initial value, a parameter's declared value)
        and is an error without one. Only user blocks may be given; added blocks always
        take their ``init`` (zeros without one)."""
        if values is not None and not isinstance(values, Mapping):
            declared = f"; declared: {list(self.by_name)}" if self.noun == "parameter" else ""
            raise BalustradeError(f"{self.owner}: {self.noun} values must be a dict name -> "
                                  f"value, got {type(values).__name__}{declared}")
        values = values or {}
        unknown = [k for k in values if k not in self.by_name or
                   self.by_name[k].origin != USER]
        if unknown:
            names = ", ".join(sorted(map(repr, unknown)))
            raise BalustradeError(f"{self.owner}: unknown {self.noun}s {names}; "
                                  f"declared: {[e.name for e in self._user]}")
        chunks = []
        for e in self.entries:
            if e.name in values:
                where = f"{self.owner}: {self.value_label} {e.name!r}"
                v = flat_value(values[e.name], e.shape, where)
                if self.noun == "parameter" and e.lb is not None and np.any(v < e.lb):
                    # a solver's own slacks come back a rounding below 0 (-4.2e-17 seen on
                    # an optimal (2.24)); SPEC §2 clips those, so values within LB_TOL of the
                    # bound are set to it and only values further below are refused
                    slack = LB_TOL * np.maximum(1.0, np.abs(e.lb))
                    bad = np.flatnonzero(v < e.lb - slack)
                    if bad.size:
                        raise BalustradeError(
                            f"{where}: must be >= {e.lb[bad[0]]:g} entrywise (shape {e.shape}), "
                            f"got {v[bad[:5]]} at flat (column-major) indices "
                            f"{bad[:5].tolist()}")
                    v = np.maximum(v, e.lb)
                chunks.append(v)
            elif e.init is not None:
                chunks.append(e.init)
            elif e.init is None and e.origin != USER:
                chunks.append(np.zeros(e.size))
            else:
                raise BalustradeError(f"{self.owner}: no value for {self.noun} {e.name!r} "
                                      f"(shape {e.shape})")
        return np.concatenate(chunks) if chunks else np.zeros(0)

    def unpack(self, w: object, user_only: bool = False) -> dict[str, np.ndarray]:
        """Split a stacked vector into named arrays of their shapes (a column ``(n, 1)`` as
        a 1-D array). ``user_only``: ``w`` may hold the added blocks too (the solver's
        full vector); only the user's blocks are returned."""
        w = as_float_array(w, f"{self.owner}: stacked {self._vector}").reshape(-1)
        expected = self.size if not user_only else None
        if expected is not None and w.size != expected:
            raise ShapeError(f"{self.owner}: stacked {self._vector}", (expected,), w.shape)
        if user_only and w.size not in (self.user_size, self.size):
            raise ShapeError(f"{self.owner}: stacked {self._vector}",
                             (self.user_size,), w.shape)
        out = {}
        for e in (self._user if user_only else self.entries):
            arr = w[e.slice].reshape(e.shape, order="F")
            out[e.name] = arr[:, 0] if e.shape[1] == 1 else arr
        return out

    @property
    def _vector(self) -> str:
        return "decision vector" if self.noun == "variable" else f"{self.noun} vector"

    # -- extension by passes -----------------------------------------------------------
    def extend(self, name: str, shape: tuple[int, int], init: object = 0.0,
               lb: object = -np.inf, ub: object = np.inf, origin: str = "pass") -> Layout:
        """A new layout with the block ``name`` (shape, initial value, bounds; scalars are
        broadcast) appended after the existing ones, marked as added by ``origin``."""
        if origin == USER:
            raise BalustradeError(f"{self.owner}: blocks added by a pass need an origin "
                                  "other than 'user'")
        if name in self.by_name:
            raise BalustradeError(f"{self.owner}: cannot add {name!r}: the layout already "
                                  "has a block of that name")
        shape = (int(shape[0]), int(shape[1]))
        n = shape[0] * shape[1]
        arrays = [np.broadcast_to(np.asarray(v, dtype=float).reshape(-1) if np.ndim(v)
                                  else float(v), (n,)).astype(float)
                  for v in (init, lb, ub)]
        entry = Entry(name, shape, slice(self.size, self.size + n), *arrays, origin=origin)
        return Layout((*self.entries, entry), self.owner, self.noun, self.value_label)

    # -- manifests ---------------------------------------------------------------------
    def to_dict(self, user_only: bool = True) -> dict[str, dict]:
        """``name -> {"offset", "shape"[, "default"][, "lb"]}`` (JSON-ready; ``default``
        for entries with an ``init``, ``lb`` for those with a lower bound, when this is a
        parameter layout)."""
        out = {}
        for e in (self._user if user_only else self.entries):
            out[e.name] = {"offset": e.slice.start, "shape": list(e.shape)}
            if self.noun == "parameter" and e.init is not None:
                out[e.name]["default"] = [float(v) for v in e.init]
            if self.noun == "parameter" and e.lb is not None:
                out[e.name]["lb"] = [float(v) for v in e.lb]
        return out

    @classmethod
    def from_dict(cls, data: Mapping[str, Mapping], owner: str = "", noun: str = "parameter",
                  value_label: str | None = None) -> Layout:
        """The layout written by :meth:`to_dict` (offsets must be stacked in order)."""
        entries, k = [], 0
        for name, lay in data.items():
            shape = (int(lay["shape"][0]), int(lay["shape"][1]))
            n = shape[0] * shape[1]
            if int(lay["offset"]) != k:
                raise BalustradeError(f"{owner}: {noun} {name!r} at offset {lay['offset']}, "
                                      f"expected {k} (blocks are stacked in order)")
            default, lb = lay.get("default"), lay.get("lb")
            entries.append(Entry(name, shape, slice(k, k + n),
                                 None if default is None else np.asarray(default, dtype=float),
                                 None if lb is None else np.asarray(lb, dtype=float)))
            k += n
        return cls(entries, owner, noun, value_label)


def _flat(value: np.ndarray | None) -> np.ndarray | None:
    return None if value is None else np.asarray(value, dtype=float).reshape(-1, order="F")


def flat_value(value: object, shape: tuple[int, int], block: str) -> np.ndarray:
    """``value`` checked to have ``shape`` (a scalar for ``(1, 1)``, a 1-D array for a row or
    column) and finite entries, flattened column-major; errors name ``block``."""
    arr = as_float_array(value, block)
    if arr.ndim == 0 and shape == (1, 1):
        arr = arr.reshape(1, 1)
    elif arr.ndim == 1 and (arr.size == shape[0] * shape[1]) and 1 in shape:
        arr = arr.reshape(shape)
    if tuple(arr.shape) != tuple(shape):
        raise ShapeError(block, shape, arr.shape)
    if not np.all(np.isfinite(arr)):
        raise NonFiniteError(f"{block}: contains NaN or inf (shape {arr.shape})")
    return arr.reshape(-1, order="F")
