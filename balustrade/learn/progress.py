"""A small progress bar with rate and ETA (no dependency).

On a terminal it redraws one line (``\\r``); otherwise (logs, CI) it prints a line at most
every ``log_interval`` seconds. Example::

    with Progress(total=3.5e5, desc="sampling", unit="samples") as bar:
        for rows in results:
            bar.update(len(rows))
"""

from __future__ import annotations

import sys
import time
from typing import TextIO


def _fmt_seconds(s: float) -> str:
    if s != s or s == float("inf"):  # NaN or infinite
        return "?"
    s = int(round(s))
    h, rem = divmod(s, 3600)
    m, sec = divmod(rem, 60)
    return f"{h}:{m:02d}:{sec:02d}" if h else f"{m:02d}:{sec:02d}"


class Progress:
    """``update(n)`` adds ``n`` units; the line shows done/total, percent, rate and ETA."""

    def __init__(self, total: float | None, desc: str = "", unit: str = "it",
                 stream: TextIO | None = None, enabled: bool = True,
                 min_interval: float = 0.2, log_interval: float = 5.0, initial: float = 0):
        self.total, self.desc, self.unit = total, desc, unit
        self.stream = sys.stderr if stream is None else stream
        self.enabled = enabled
        self.tty = bool(getattr(self.stream, "isatty", lambda: False)())
        self.interval = min_interval if self.tty else log_interval
        self.n = float(initial)
        self._start_n = float(initial)
        self.start = time.perf_counter()
        self._last = -float("inf")

    @property
    def rate(self) -> float:
        elapsed = time.perf_counter() - self.start
        return (self.n - self._start_n) / elapsed if elapsed > 0 else 0.0

    @property
    def eta(self) -> float:
        if not self.total or self.rate <= 0:
            return float("nan")
        return max(self.total - self.n, 0.0) / self.rate

    def line(self) -> str:
        done = f"{int(self.n)}" + (f"/{int(self.total)}" if self.total else "")
        pct = f" [{100.0 * self.n / self.total:5.1f}%]" if self.total else ""
        elapsed = time.perf_counter() - self.start
        return (f"{self.desc + ': ' if self.desc else ''}{done} {self.unit}{pct} "
                f"{self.rate:.1f} {self.unit}/s elapsed {_fmt_seconds(elapsed)} "
                f"ETA {_fmt_seconds(self.eta)}")

    def update(self, n: float = 1) -> None:
        self.n += n
        now = time.perf_counter()
        if self.enabled and now - self._last >= self.interval:
            self._last = now
            self._write()

    def _write(self, final: bool = False) -> None:
        if self.tty:
            self.stream.write("\r" + self.line() + ("\n" if final else ""))
        else:
            self.stream.write(self.line() + "\n")
        self.stream.flush()

    def close(self) -> None:
        if self.enabled:
            self._write(final=True)
            self.enabled = False

    def __enter__(self) -> Progress:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
