"""Audit E: the regret syntheses of the rocket example (T=8 for time) on their defaults
(lmi="banded", target None) vs lmi="split" (another LMI form) — levels and certificates."""
import time

from balustrade.models.rocket import RocketRegretSetup
from balustrade.reproduce.rocket_regret import synthesis_makers

s = RocketRegretSetup(T=8)
d, ops, cons = synthesis_makers(s)
o, _, _ = synthesis_makers(s, lmi="split")
for name in d:
    t = time.process_time(); a = d[name](); ta = time.process_time() - t
    t = time.process_time(); b = o[name](); tb = time.process_time() - t
    ca, cb = a.info.get("certificate", {}), b.info.get("certificate", {})
    rel = abs(a.level - b.level) / max(1e-12, abs(b.level)) if a.level is not None and b.level is not None else None
    print(f"{name:6s} default: {a.status} level {a.level} lmi {a.info.get('lmi')} cert {ca.get('kind')} consistent {ca.get('consistent')} ({ta:.1f}s) | "
          f"split: {b.status} level {b.level} cert {cb.get('kind')} consistent {cb.get('consistent')} ({tb:.1f}s) | rel {rel}")
