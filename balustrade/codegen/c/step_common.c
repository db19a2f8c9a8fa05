/* bal/step_common.c: input checks and the box projection shared by the control steps
 * (bal/pcbf.c, bal/approx.c, bal/grid.c, bal/robust.c, bal/multiobj.c; one step per
 * translation unit). */
#include <math.h>

/* 1 if the n values are all finite */
static int bal_finite(const casadi_real* v, casadi_int n) {
  casadi_int i;
  for (i = 0; i < n; ++i) {
    if (!isfinite(v[i])) return 0;
  }
  return 1;
}

/* out := u_p with its NaN or inf entries read as 0 (finite_proposal of
   balustrade.control.fallbacks: the filter still certifies what is applied); returns how
   many entries were replaced */
static int bal_read_proposal(const casadi_real* u_p, casadi_real* out, casadi_int n) {
  casadi_int i;
  int replaced = 0;
  for (i = 0; i < n; ++i) {
    replaced += !isfinite(u_p[i]);
    out[i] = isfinite(u_p[i]) ? u_p[i] : 0.0;
  }
  return replaced;
}

/* out := u clipped to the box [lb, ub] (n values); a NaN entry counts as 0 (the steps pass
   proposals with non-finite entries already read as 0; a NaN would otherwise make fmax
   silently pick the lower bound) */
static void bal_clip(const casadi_real* u, const casadi_real* lb, const casadi_real* ub,
                     casadi_real* out, casadi_int n) {
  casadi_int i;
  casadi_real v;
  for (i = 0; i < n; ++i) {
    v = isnan(u[i]) ? 0.0 : u[i];
    out[i] = fmin(fmax(v, lb[i]), ub[i]);
  }
}
