"""Audit E: ellipsoidal_rpi refuses a set whose is_rpi miss exceeds RPI_REPAIR (1e-4) and
repairs one below it: is_rpi replaced by a stand-in whose margin for the uninflated set is
given, and which reports the true (S-lemma) margin of an inflated one."""
import balustrade.design.rpi as R
from balustrade.dsl.error_sets import RPICheck
from balustrade.dsl.error_sets import is_rpi as real
from balustrade.models.unstable2d import unstable2d, unstable2d_setup

system, s = unstable2d(), unstable2d_setup(10)
for fake in (2e-4, 1.01e-4, 9e-5, 1e-6):
    calls = []
    def stand_in(E, A_cl, W, G=None, **kw):
        calls.append(E.P.copy())
        if len(calls) == 1:  # the first check of the best candidate
            return RPICheck(False, fake, "stand-in", {})
        r = real(E, A_cl, W, G)
        return r
    R.is_rpi = stand_in
    try:
        e = R.ellipsoidal_rpi(system.A, system.B, s.W, s.X, s.U)
        print(f"miss {fake:.2e}: accepted, inflation {e.info['inflation']:.6f}, real margin after: {real(e.E, system.A + system.B @ e.K, s.W).margin:.2e}")
    except Exception as ex:
        print(f"miss {fake:.2e}: refused ({type(ex).__name__}: {str(ex)[:90]})")
R.is_rpi = real
