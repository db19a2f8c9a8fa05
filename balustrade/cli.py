"""The ``balustrade`` command: demo, reproduce, bench (and what later layers add)."""

from __future__ import annotations

import argparse
import importlib.util
import json
import sys
from pathlib import Path

from balustrade.errors import BalustradeError


def _cmd_demo(args: argparse.Namespace) -> int:
    from balustrade.reproduce import run

    out = Path(args.out)
    metrics = run("pendulum", out, quick=args.quick)
    print(metrics.get("summary_table", json.dumps(metrics, indent=1)[:2000]))
    print(f"\nplots and metrics written to {out.resolve()}")
    for plot in metrics.get("plots", []):
        print(f"  plot: {plot}")
    return 0


def _cmd_reproduce(args: argparse.Namespace) -> int:
    from balustrade.reproduce import registry, run

    if args.name == "list":
        print("\n".join(sorted(registry())))
        return 0
    out = Path(args.out) if args.out else Path("out") / args.name
    metrics = run(args.name, out, quick=args.quick)
    if "summary_table" in metrics:
        print(metrics["summary_table"])
    print(f"\nmetrics and plots written to {out.resolve()}")
    return 0


def _benchmark_dir() -> Path:
    here = Path(__file__).resolve().parent.parent / "benchmarks"
    if not here.is_dir():
        raise BalustradeError(f"benchmarks folder not found at {here} (run from a source checkout)")
    return here


def _cmd_bench(args: argparse.Namespace) -> int:
    rows = []
    paths = sorted(_benchmark_dir().glob("bench_*.py"))
    if args.only:
        unmatched = [key for key in args.only if not any(key in p.stem for p in paths)]
        if unmatched:  # a typo ran nothing and exited 0 before (session 15 docs audit)
            raise BalustradeError(f"bench --only: no benchmark matches {unmatched}; the "
                                  f"benchmarks are {[p.stem for p in paths]}")
    for path in paths:
        if args.only and not any(key in path.stem for key in args.only):
            continue
        spec = importlib.util.spec_from_file_location(path.stem, path)
        module = importlib.util.module_from_spec(spec)
        assert spec.loader is not None
        spec.loader.exec_module(module)
        print(f"== {path.stem}", flush=True)
        for row in module.run(quick=args.quick):
            rows.append(row)
            print(_format_row(row), flush=True)
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=1))
    return 0


def _format_row(row: dict) -> str:
    parts = [f"{row['name']:<52}"]
    if "median_s" in row:
        parts.append(f"median {_fmt_time(row['median_s'])}")
    if "baseline" in row:
        parts.append(f"vs {row['baseline']}: {row['ratio']:.1f}x faster")
    extra = {k: v for k, v in row.items() if k not in {"name", "median_s", "baseline", "ratio"}}
    if extra:
        parts.append(" ".join(f"{k}={v}" for k, v in extra.items()))
    return "  ".join(parts)


def _fmt_time(seconds: float) -> str:
    if seconds < 1e-3:
        return f"{seconds * 1e6:8.1f} us"
    if seconds < 1:
        return f"{seconds * 1e3:8.2f} ms"
    return f"{seconds:8.2f} s "


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="balustrade", description="balustrade: safe predictive control. Run the "
        "pendulum demo, reproduce a thesis example, run the benchmarks, emit C, sample and "
        "train a learned PCBF; '<command> --help' for the options of each.")
    sub = parser.add_subparsers(dest="command", required=True)

    demo = sub.add_parser("demo", help="the pendulum PCBF safety filter, end to end")
    demo.add_argument("--out", default="out/demo",
                      help="folder for metrics.json and the plot (default out/demo)")
    demo.add_argument("--quick", action="store_true", help="fewer steps (60 instead of 150)")
    demo.set_defaults(func=_cmd_demo)

    rep = sub.add_parser("reproduce", help="reproduce a thesis example ('list' lists them)")
    rep.add_argument("name", help="a name of 'balustrade reproduce list', or 'list'")
    rep.add_argument("--out", default=None,
                     help="folder for metrics.json and the plots (default out/NAME)")
    rep.add_argument("--quick", action="store_true",
                     help="a shorter run (what it shortens: docs/ of that example)")
    rep.set_defaults(func=_cmd_reproduce)

    bench = sub.add_parser("bench", help="run benchmarks/ and print medians and ratios")
    bench.add_argument("--quick", action="store_true", help="fewer samples per row")
    bench.add_argument("--only", nargs="*", default=None, help="substrings of benchmark names")
    bench.add_argument("--json", default=None, help="also write the rows to this file")
    bench.set_defaults(func=_cmd_bench)

    for extra in ("balustrade.examples.codegen_cli", "balustrade.learn.cli"):
        if importlib.util.find_spec(extra) is not None:
            importlib.import_module(extra).register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except BalustradeError as exc:
        print(f"balustrade: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
