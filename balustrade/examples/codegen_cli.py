"""``balustrade codegen NAME --out DIR``: write C sources, a Makefile and a main.c example.

``NAME`` is one of :data:`balustrade.examples.codegen.TARGETS` (``list`` lists them).
``--build`` also compiles the shared library and ``main`` (``-Wall -Wextra -Werror``) and
``--run`` runs ``main`` (the closed loop in C, with timings).
"""

from __future__ import annotations

import argparse
import subprocess
from pathlib import Path

from balustrade.errors import CodegenError


def _cmd_codegen(args: argparse.Namespace) -> int:
    from balustrade.codegen.build import build, build_executable
    from balustrade.examples.codegen import TARGETS

    if args.name == "list":
        print("\n".join(sorted(TARGETS)))
        return 0
    if args.name not in TARGETS:
        raise CodegenError(f"unknown codegen target {args.name!r}; available: "
                           f"{', '.join(sorted(TARGETS))}")
    out = Path(args.out) if args.out else Path("out") / "codegen" / args.name
    emitted = TARGETS[args.name](out)
    files = sorted(p.name for p in out.iterdir() if p.is_file())
    print(f"wrote {len(files)} files to {out.resolve()}: {', '.join(files)}")
    if (out / "Makefile").exists():
        print(f"build and run in C:  make -C {out} run    (valgrind: make -C {out} valgrind)")
    else:
        print(f"build:  cd {out} && cc -O3 -Wall -Wextra -fPIC -shared -o lib{emitted.name}.so "
              f"{emitted.name}.c {emitted.name}_casadi.c -lm")
    if args.build or args.run:
        lib = build(out, emitted.name, werror=True)
        print(f"built {lib}")
        if (out / "main.c").exists():
            exe = build_executable(out)
            print(f"built {exe}")
            if args.run:
                proc = subprocess.run([str(exe)], capture_output=True, text=True, check=False)
                print(proc.stdout, end="")
                if proc.returncode:
                    raise CodegenError(f"{exe} exited with {proc.returncode}: {proc.stderr}")
    return 0


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add the ``codegen`` subcommand to the ``balustrade`` command."""
    p = subparsers.add_parser("codegen", help="emit C sources (+ Makefile, main.c) for a "
                                              "target ('list' lists them)")
    p.add_argument("name", help="target name, e.g. pendulum_pcbf, or 'list'")
    p.add_argument("--out", default=None, help="output folder (default out/codegen/NAME)")
    p.add_argument("--build", action="store_true", help="also compile the library and main")
    p.add_argument("--run", action="store_true", help="also build and run main")
    p.set_defaults(func=_cmd_codegen)
