"""Compile emitted C with the system C compiler (``$CC``, else ``cc`` on ``PATH``)."""

from __future__ import annotations

import os
import shutil
import subprocess
from pathlib import Path

from balustrade.errors import CodegenError

#: Flags of every build: optimized, position independent, all warnings, and no contraction
#: of a product and a sum into one fused multiply-add (``-ffp-contract=off``): CasADi's
#: evaluation in Python rounds every operation, so a fused C (GCC's default where the target
#: has FMA: ``-march=native`` on x86-64, any aarch64) would round differently and C = Python
#: would no longer be bitwise (docs/vehicles.md, "Session 13: C = Python along loops").
FP_FLAGS = ("-ffp-contract=off",)
BASE_FLAGS = ("-O3", *FP_FLAGS, "-fPIC", "-Wall", "-Wextra")
#: CasADi's generated memory pools hold one user per function unless told otherwise; the
#: Python runtime may hold several work structs of the same library at once.
THREAD_FLAGS = ("-DCASADI_MAX_NUM_THREADS=8",)


def find_compiler() -> str:
    """The C compiler: ``$CC`` if set (must exist), else ``cc`` on ``PATH``."""
    env = os.environ.get("CC")
    if env:
        exe = env.split()[0]
        found = shutil.which(exe)
        if found is None:
            raise CodegenError(f"C compiler $CC={env!r} not found; set CC to a C compiler "
                               "(e.g. cc, gcc, clang) or unset it to use cc from PATH")
        return found
    found = shutil.which("cc") or shutil.which("gcc") or shutil.which("clang")
    if found is None:
        raise CodegenError("no C compiler found (looked for $CC, cc, gcc, clang on PATH); "
                           "install one, e.g. `apt-get install gcc`, or set CC")
    return found


def _sources(src_dir: Path, main: str = "main.c") -> list[Path]:
    """The library sources of ``src_dir``: every ``*.c`` except ``main.c`` and ``main``."""
    return sorted(p for p in src_dir.glob("*.c") if p.name not in ("main.c", Path(main).name))


def _src_dir(src_dir: str | Path, what: str) -> Path:
    """``src_dir`` as an existing folder, else a CodegenError naming it."""
    if not isinstance(src_dir, (str, os.PathLike)):
        raise CodegenError(f"{what}: src_dir must be a path, got {type(src_dir).__name__}")
    path = Path(src_dir)
    if not path.is_dir():
        raise CodegenError(f"{what}: {str(path)!r} is not a folder of emitted sources")
    return path


def _flags(extra_flags: object, what: str) -> tuple[str, ...]:
    """``extra_flags`` as a tuple of strings (one flag each), else a CodegenError: a plain
    string would be splatted into one flag per character."""
    if isinstance(extra_flags, str) or not isinstance(extra_flags, (tuple, list)) or \
            not all(isinstance(f, str) for f in extra_flags):
        raise CodegenError(f"{what}: extra_flags must be a tuple of strings (one flag each), "
                           f"got {extra_flags!r}")
    return tuple(extra_flags)


def _run(cmd: list[str], what: str) -> None:
    try:
        proc = subprocess.run(cmd, capture_output=True, text=True, check=False)
    except OSError as exc:
        raise CodegenError(f"{what}: could not run {cmd[0]!r}: {exc}") from exc
    if proc.returncode != 0:
        raise CodegenError(f"{what} failed (exit {proc.returncode}):\n  {' '.join(cmd)}\n"
                           f"{proc.stderr.strip()[-4000:]}")


def build(src_dir: str | Path, name: str | None = None, werror: bool = False,
          extra_flags: tuple[str, ...] | list[str] = (), out: str | Path | None = None) -> Path:
    """Compile every ``*.c`` in ``src_dir`` except ``main.c`` into a shared library
    (``cc -O3 -ffp-contract=off -fPIC -shared -Wall -Wextra [-Werror] ... -lm``) and return its path
    (default ``src_dir/lib<name>.so``; ``name`` defaults to the folder's manifest)."""
    src_dir = _src_dir(src_dir, "build")
    extra_flags = _flags(extra_flags, "build")
    sources = _sources(src_dir)
    if not sources:
        raise CodegenError(f"no C sources in {src_dir}")
    if name is None:
        manifests = sorted(src_dir.glob("*.json"))
        name = manifests[0].stem if manifests else src_dir.name
    cc = find_compiler()
    target = Path(out) if out is not None else src_dir / f"lib{name}.so"
    cmd = [cc, *BASE_FLAGS, *THREAD_FLAGS, *(["-Werror"] if werror else []), "-shared",
           *extra_flags, "-o", str(target), *map(str, sources), "-lm"]
    _run(cmd, f"building {target.name}")
    return target


def build_executable(src_dir: str | Path, main: str = "main.c", werror: bool = True,
                     extra_flags: tuple[str, ...] | list[str] = (),
                     out: str | Path | None = None) -> Path:
    """Compile ``main.c`` with the other sources of ``src_dir`` into an executable
    (``-Wall -Wextra -Werror`` by default, as the generated Makefile does)."""
    src_dir = _src_dir(src_dir, "build_executable")
    extra_flags = _flags(extra_flags, "build_executable")
    if not (src_dir / main).is_file():
        raise CodegenError(f"build_executable: no {main!r} in {src_dir} (write_example writes "
                           "main.c)")
    cc = find_compiler()
    target = Path(out) if out is not None else src_dir / Path(main).stem
    cmd = [cc, "-O3", *FP_FLAGS, "-Wall", "-Wextra", *(["-Werror"] if werror else []),
           *extra_flags,
           "-o", str(target), str(src_dir / main), *map(str, _sources(src_dir, main)), "-lm"]
    _run(cmd, f"building {target.name}")
    return target


def run_under_valgrind(exe: str | Path, *args: str, suppressions: str | Path | None = None,
                       timeout: float = 900) -> subprocess.CompletedProcess:
    """Run an emitted controller's executable under valgrind's memcheck: full leak check,
    exit code 9 on any memory error or *definite* leak (the check every emitted controller
    passes, docs/deploy_c.md), optionally with a ``suppressions`` file for a linked solver
    library. Returns the finished process (``returncode == 0``: clean)."""
    if shutil.which("valgrind") is None:
        raise CodegenError("run_under_valgrind: valgrind is not installed")
    cmd = ["valgrind", "--error-exitcode=9", "--leak-check=full",
           "--errors-for-leak-kinds=definite",
           *([f"--suppressions={suppressions}"] if suppressions is not None else []),
           str(exe), *map(str, args)]
    return subprocess.run(cmd, capture_output=True, text=True, timeout=timeout, check=False)
