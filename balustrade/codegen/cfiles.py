"""balustrade's static C and the few generated lines that instantiate it.

The algorithms of the emitted C — one problem's solve with its retries and the
``BAL_FEASIBLE`` rule, the PCBF step (2.24)+(2.23) with its fallback ladder, Algorithm 7.5
with its screened multi-start (stable sort, ``numpy.allclose`` emulation), the closed-loop
example — are real C files shipped as package data in ``balustrade/codegen/c/`` and copied
unchanged into ``<out_dir>/bal/``. They are written once against a symbol prefix
(``BAL_PROBLEM``, ``BAL_STEP``; see ``c/common.h``). An emitted module ``<name>`` adds:

* ``<name>_config.h`` — numbers only, every line a comment or a ``#define``: sizes,
  offsets, bounds, tolerances, the CasADi functions of each problem, status codes
  (:mod:`~balustrade.codegen.status`);
* ``<name>.h`` / ``<name>.c`` — glue: which static file is instantiated under which
  prefix (a few ``#define``/``#include`` lines);
* ``<name>_casadi.c/.h`` — CasADi's code generation (solvers and functions).
"""

from __future__ import annotations

import shutil
from importlib import resources
from pathlib import Path

import numpy as np

from balustrade.codegen import status as S

#: the folder of the emitted module that receives the static files
SUBDIR = "bal"
#: the static files copied into ``<out_dir>/bal/`` (``#include``\\ d by the glue)
STATIC = ("common.h", "problem.h", "problem.c", "step_common.c", "pcbf.h", "pcbf.c",
          "h_common.c", "approx.h", "approx.c", "approx_net.c", "grid.h", "grid.c",
          "tube_common.c", "robust.h", "robust.c", "multiobj.h", "multiobj.c", "rapsf.h",
          "rapsf.c", "multiobj_lyap.h", "multiobj_lyap.c", "rapsf_hot.h", "rapsf_hot.c")
#: the entry points each static header declares (``<prefix>_<entry>``), listed by their real
#: names in the generated ``<name>.h`` (checked against the built library by the tests)
ENTRY_POINTS: dict[str, tuple[str, ...]] = {
    "problem": ("init", "finalize", "alloc", "free", "cold_start", "warm_start",
                "warm_start_primal", "solve", "primal", "value", "residuals"),
    "pcbf": ("init", "finalize", "alloc", "free", "reset", "step", "slack_problem",
             "filter_problem", "solve_status", "h_upper", "proposal_replaced"),
    "approx": ("init", "finalize", "alloc", "free", "reset", "step", "set_certify", "dh",
               "proposal_replaced", "counter", "inaccurate"),
    "grid": ("init", "finalize", "alloc", "free", "reset", "step", "n_candidates",
             "proposal_replaced", "counter", "u_prev"),
    "robust": ("init", "finalize", "alloc", "free", "reset", "step", "slack_problem",
               "filter_problem", "solve_status", "h_cand", "proposal_replaced",
               "candidate_exact"),
    "multiobj": ("init", "finalize", "alloc", "free", "reset", "step", "slack_problem",
                 "main_problem", "solve_status", "values", "proposal_replaced",
                 "candidate_exact"),
    "rapsf": ("init", "finalize", "alloc", "free", "reset", "step", "main_problem",
              "solve_status", "k_inf", "objective", "proposal_replaced", "inaccurate"),
    "rapsf_hot": ("init", "finalize", "alloc", "free", "reset", "step", "solve_status",
                  "k_inf", "objective", "proposal_replaced", "qp_info", "qp_primal",
                  "qp_dual"),
    "multiobj_lyap": ("init", "finalize", "alloc", "free", "reset", "step", "init_problem",
                      "main_problem", "solve_status", "values", "proposal_replaced"),
}
#: values per line of an array macro
_PER_LINE = 6


def static_path(fname: str) -> Path:
    """The packaged static file ``fname`` (``balustrade/codegen/c/<fname>``)."""
    return Path(str(resources.files("balustrade.codegen").joinpath("c", fname)))


def static_text(fname: str) -> str:
    """The text of the packaged static file ``fname``."""
    return static_path(fname).read_text()


def copy_static(out_dir: Path) -> list[Path]:
    """Copy the static C into ``out_dir/bal/`` (identical for every module: several modules
    may share a folder) and return the copied paths."""
    dest = out_dir / SUBDIR
    dest.mkdir(exist_ok=True)
    paths = []
    for fname in STATIC:
        target = dest / fname
        shutil.copyfile(static_path(fname), target)
        paths.append(target)
    return paths


# -- C literals ------------------------------------------------------------------------
def c_double(v: float) -> str:
    """A double as a C literal (``repr`` round-trips; NaN and inf as ``math.h`` macros)."""
    if np.isnan(v):
        return "NAN"
    if np.isinf(v):
        return "INFINITY" if v > 0 else "-INFINITY"
    return repr(float(v))


def c_array(values: np.ndarray | list[float], min_len: int = 1) -> str:
    """``{a, b, ...}``: an initializer of doubles (padded with zeros to ``min_len``)."""
    vals = [float(v) for v in np.asarray(values, dtype=float).reshape(-1)]
    if len(vals) < min_len:
        vals += [0.0] * (min_len - len(vals))
    return "{" + ", ".join(c_double(v) for v in vals) + "}"


class Config:
    """The lines of a generated config header: only comments and ``#define``\\ s, so that
    every decision stays in the static C."""

    def __init__(self) -> None:
        self.lines: list[str] = []

    def comment(self, text: str) -> None:
        """A block comment (``text`` may span lines)."""
        body = text.strip("\n").split("\n")
        if len(body) == 1:
            self.lines.append(f"/* {body[0]} */")
            return
        self.lines.append("/* " + body[0])
        self.lines += [(" * " + line).rstrip() for line in body[1:]]
        self.lines.append(" */")

    def define(self, name: str, value: object, doc: str | None = None) -> None:
        line = f"#define {name} {value}"
        self.lines.append(line + (f"  /* {doc} */" if doc else ""))

    def array(self, name: str, values: np.ndarray | list[float], min_len: int = 1) -> None:
        """``#define name {...}``, continued over lines of a few values."""
        vals = [c_double(v) for v in np.asarray(values, dtype=float).reshape(-1)]
        vals += ["0.0"] * (min_len - len(vals))
        self._braced(name, [", ".join(vals[k: k + _PER_LINE])
                            for k in range(0, len(vals), _PER_LINE)])

    def matrix(self, name: str, rows: np.ndarray) -> None:
        """``#define name {{row 0}, {row 1}, ...}``, one row per line."""
        self._braced(name, [c_array(r) for r in np.atleast_2d(rows)])

    def _braced(self, name: str, chunks: list[str]) -> None:
        if len(chunks) <= 1:
            self.define(name, "{" + "".join(chunks) + "}")
            return
        self.lines.append(f"#define {name} {{ \\")
        self.lines += [f"  {c}," + " \\" for c in chunks[:-1]]
        self.lines.append(f"  {chunks[-1]}}}")

    def xmacro(self, name: str, items: list[str]) -> None:
        """``#define name(X) X(a) X(b) ...`` (an X-macro: the static C says what ``X`` is)."""
        self.define(f"{name}(X)", " ".join(f"X({it})" for it in items))

    def status(self, family: tuple[S.Status, ...], guard: str) -> None:
        """The ``#define``\\ s of a status family (:mod:`~balustrade.codegen.status`),
        guarded so that the headers of several modules can be included together."""
        self.lines += [f"#ifndef {guard}", f"#define {guard}"]
        self.lines += S.c_defines(family).rstrip("\n").split("\n")
        self.lines.append("#endif")

    def blank(self) -> None:
        self.lines.append("")

    def text(self) -> str:
        return "\n".join(self.lines) + "\n"


# -- the generated files of one module ---------------------------------------------------
def config_header(name: str, what: str, body: Config) -> str:
    """``<name>_config.h``: the numbers of module ``name`` (``body``) and the solve
    statuses, under an include guard."""
    guard = f"{name.upper()}_CONFIG_H"
    cfg = Config()
    cfg.comment(f"{name}_config.h: the numbers of\n{what}, generated by balustrade.\n"
                "Only #defines: the algorithms are the static files of bal/ (see bal/common.h),\n"
                f"instantiated by {name}.c. Doubles are stored column-major (Fortran order).")
    cfg.lines += [f"#ifndef {guard}", f"#define {guard}", ""]
    cfg.comment("Status of one solve (return value of <problem>_solve).")
    cfg.status(S.SOLVE, "BAL_STATUS_CODES")
    cfg.blank()
    cfg.lines += body.lines
    cfg.lines += ["", f"#endif /* {guard} */"]
    return cfg.text()


def _instances(parts: list[tuple[str, str]], ext: str) -> list[str]:
    lines = []
    for kind, prefix in parts:
        macro = "BAL_PROBLEM" if kind == "problem" else "BAL_STEP"
        lines += [f"#define {macro} {prefix}", f'#include "{SUBDIR}/{kind}.{ext}"',
                  f"#undef {macro}"]
    return lines


def glue_header(name: str, what: str, parts: list[tuple[str, str]]) -> str:
    """``<name>.h``: the CasADi header, the config, then each static header under its
    prefix (``parts``: ``(kind, prefix)`` with kind ``problem``, ``pcbf`` or ``approx``)."""
    guard = f"{name.upper()}_H"
    listing = ""
    for kind, prefix in parts:
        listing += f"\n *   bal/{kind}.h with the prefix {prefix} (work struct {prefix}_work):"
        names = [f"{prefix}_{e}" for e in ENTRY_POINTS[kind]]
        for k in range(0, len(names), 2):
            listing += "\n *     " + ", ".join(names[k: k + 2]) + (
                "," if k + 2 < len(names) else "")
    lines = [
        f"/* {name}.h: C entry points generated by balustrade from",
        f" * {what}.",
        " *",
        f" * Self-contained: compile {name}.c and {name}_casadi.c (bal/ next to them) with any",
        " * C99 compiler and link with libm. Every array is caller-owned or preallocated in a",
        " * work struct; no call allocates except the optional *_alloc convenience functions",
        " * (calloc). Doubles are stored column-major (Fortran order), as in CasADi.",
        f" * Entry points (declared by the static headers of bal/):{listing}"
        if parts else f" * Entry points: the CasADi functions of {name}_casadi.h.",
        " */",
        f"#ifndef {guard}", f"#define {guard}", "",
        f'#include "{name}_casadi.h"', f'#include "{name}_config.h"',
        f'#include "{SUBDIR}/common.h"', "",
        "#ifdef __cplusplus", 'extern "C" {', "#endif", "",
        *_instances(parts, "h"), "",
        "#ifdef __cplusplus", '} /* extern "C" */', "#endif", "",
        f"#endif /* {guard} */"]
    return "\n".join(lines) + "\n"


def glue_source(name: str, parts: list[tuple[str, str]]) -> str:
    """``<name>.c``: each static source under its prefix."""
    lines = [f"/* {name}.c: balustrade's static C (bal/) instantiated for {name}, around the",
             f" * CasADi-generated {name}_casadi.c. */", f'#include "{name}.h"', "",
             *_instances(parts, "c")]
    return "\n".join(lines) + "\n"


def example_header(name: str, n_init: int, steps: int, x_init: np.ndarray,
                   u_p: np.ndarray) -> str:
    """``example.h``: the data of the closed-loop example ``main.c`` of module ``name``."""
    cfg = Config()
    cfg.comment(f"example.h: data of the closed-loop example main.c of {name} (generated by\n"
                "balustrade.codegen.write_example).")
    cfg.lines += ["#ifndef BAL_EXAMPLE_H", "#define BAL_EXAMPLE_H", f'#include "{name}.h"']
    cfg.define("BAL_STEP", name)
    cfg.define("N_INIT", n_init, "initial states")
    cfg.define("STEPS", steps, "steps per closed loop")
    cfg.matrix("X_INIT", x_init)
    cfg.array("U_PROP", u_p)
    cfg.lines.append("#endif")
    return cfg.text()


def makefile(name: str) -> str:
    """The example's ``Makefile``: ``NAME = <name>`` and the static ``c/Makefile.in``."""
    return f"NAME = {name}\n" + static_text("Makefile.in")
