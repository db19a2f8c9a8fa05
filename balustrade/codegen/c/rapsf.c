/* bal/rapsf.c: the Algorithm 4.1 control step Q = BAL_STEP (bal/rapsf.h) with the fallbacks
 * of balustrade.control.rapsf.RAPSF. Included by the generated <name>.c after the problem
 * Q_main. From <name>_config.h: Q_NX, Q_NU, Q_N, Q_NQ, Q_NTH, Q_NXR, the tube gain Q_K
 * (NU x NX, column-major), Q_WARM_START (1: (4.5) starts from the previous step's solution
 * after a converged solve), the offsets of Q_main (Q_main_P_x0, ..., Q_main_W_v) and, for
 * Remark 4.6, Q_SHRINKING with the X-macro Q_SHRUNK(X) = X(shrunk1, 1) ... of the problems
 * (4.5) with the horizons 1 ... N-1 (same parameter layout as Q_main), and the backup
 * policy Q_BACKUP (0: K x; 1: Q_KB, Q_KB0 of K_b x + k_b; 2: the function Q_backup_policy).
 */
#include <math.h>
#include <stdlib.h>
#include <string.h>

#include "step_common.c"

static const casadi_real BAL_QX(gain)[BAL_QX(NU) * BAL_QX(NX)] = BAL_QX(K);
#if BAL_QX(BACKUP) == 1
static const casadi_real BAL_QX(backup_gain)[BAL_QX(NU) * BAL_QX(NX)] = BAL_QX(KB);
static const casadi_real BAL_QX(backup_offset)[BAL_QX(NU)] = BAL_QX(KB0);
#endif

int BAL_QX(init)(BAL_QX(work)* wk) {
  int failed = 0; /* the horizon whose init failed (0: none) */
  wk->ready = 0;
  if (BAL_QX(main_init)(&wk->main)) return -1;
#define BAL_RAPSF_SHRUNK_INIT(tag, h) \
  if (!failed && BAL_QX(tag##_init)(&wk->tag)) failed = h;
  BAL_QX(SHRUNK)(BAL_RAPSF_SHRUNK_INIT)
#undef BAL_RAPSF_SHRUNK_INIT
#if BAL_QX(BACKUP) == 2
  if (!failed) { /* the backup function's memory; on failure undo every horizon */
    BAL_QX(backup_policy_incref)();
    wk->bmem = BAL_QX(backup_policy_checkout)();
    if (wk->bmem < 0) {
      BAL_QX(backup_policy_decref)();
      failed = BAL_QX(N);
    }
  }
#endif
  if (failed) { /* give back what was taken */
#define BAL_RAPSF_SHRUNK_UNDO(tag, h) \
  if (h < failed) BAL_QX(tag##_finalize)(&wk->tag);
    BAL_QX(SHRUNK)(BAL_RAPSF_SHRUNK_UNDO)
#undef BAL_RAPSF_SHRUNK_UNDO
    BAL_QX(main_finalize)(&wk->main);
    return -1;
  }
  BAL_QX(reset)(wk);
  wk->ready = 1;
  return 0;
}

void BAL_QX(finalize)(BAL_QX(work)* wk) {
  if (!wk->ready) return;
#if BAL_QX(BACKUP) == 2
  BAL_QX(backup_policy_release)(wk->bmem);
  BAL_QX(backup_policy_decref)();
#endif
#define BAL_RAPSF_SHRUNK_FINALIZE(tag, h) BAL_QX(tag##_finalize)(&wk->tag);
  BAL_QX(SHRUNK)(BAL_RAPSF_SHRUNK_FINALIZE)
#undef BAL_RAPSF_SHRUNK_FINALIZE
  BAL_QX(main_finalize)(&wk->main);
  wk->ready = 0;
}

BAL_DEFINE_ALLOC_FREE(BAL_QX)

void BAL_QX(reset)(BAL_QX(work)* wk) {
  (void) bal_clip; /* bal/step_common.c's box projection: no box fallback here */
  BAL_QX(main_cold_start)(&wk->main);
  wk->have_plan = 0;
  wk->k_inf = BAL_QX(N) - 1;
  wk->main_status = BAL_NOT_RUN;
  wk->shrunk_status = BAL_NOT_RUN;
  wk->main_inaccurate = wk->shrunk_inaccurate = 0;
  wk->n_replaced = 0;
  wk->objective = NAN;
}

/* u := K x + v (v may be 0: the backup policy K x); NaN entries of x count as 0 */
static void BAL_QX(feedback)(const casadi_real* x, const casadi_real* v, casadi_real* u) {
  casadi_int i, j;
  casadi_real xj;
  for (i = 0; i < BAL_QX(NU); ++i) {
    u[i] = v ? v[i] : 0.0;
    for (j = 0; j < BAL_QX(NX); ++j) {
      xj = isfinite(x[j]) ? x[j] : 0.0;
      u[i] += BAL_QX(gain)[i + j * BAL_QX(NU)] * xj;
    }
  }
}

/* the backup policy pi_Cf at x, NaN entries of x as 0 (RAPSF._backup): Q_BACKUP 0 the
   default K x, 1 the affine law K_b x + k_b, 2 the function Q_backup_policy(x) (NaN outputs
   when it fails or there is no work memory) */
static void BAL_QX(apply_backup)(const casadi_real* x, casadi_real* u, BAL_QX(work)* wk) {
#if BAL_QX(BACKUP) == 0
  (void) wk;
  BAL_QX(feedback)(x, 0, u);
#elif BAL_QX(BACKUP) == 1
  casadi_int i, j;
  (void) wk;
  for (i = 0; i < BAL_QX(NU); ++i) {
    u[i] = BAL_QX(backup_offset)[i];
    for (j = 0; j < BAL_QX(NX); ++j) {
      u[i] += BAL_QX(backup_gain)[i + j * BAL_QX(NU)] * (isfinite(x[j]) ? x[j] : 0.0);
    }
  }
#else
  casadi_int i;
  if (wk && wk->ready) {
    for (i = 0; i < BAL_QX(NX); ++i) wk->bx[i] = isfinite(x[i]) ? x[i] : 0.0;
    wk->barg[0] = wk->bx;
    wk->bres[0] = u;
    if (!BAL_QX(backup_policy)(wk->barg, wk->bres, wk->biw, wk->bw, wk->bmem)) return;
  }
  for (i = 0; i < BAL_QX(NU); ++i) u[i] = NAN;
#endif
}

#if BAL_QX(SHRINKING)
/* Remark 4.6: (4.5) with the horizon h = N - k_inf (1 <= h <= N - 1) at the parameters
   wk->p, from a cold start as every solve; BAL_OK -> its v^ becomes the stored plan from
   stage k_inf on (plan[k_inf + i] = v^_i: the state now follows its tube, which ends in C_f
   at the old plan's time, so k_inf keeps counting; RAPSF._store_shrunk) and
   u_out = K x + v^_0. Returns 1 if it was used: BAL_OK, and not a stop at the solver's
   acceptable level (Q_inaccurate 1: RAPSF uses only an optimal solve), else 0. */
static int BAL_QX(solve_shrunk)(BAL_QX(work)* wk, int h, const casadi_real* x,
                                casadi_real* u_out) {
  int st = BAL_NOT_RUN, inaccurate = 0;
#define BAL_RAPSF_SHRUNK_SOLVE(tag, hh)                                     \
  if (h == hh) {                                                            \
    BAL_QX(tag##_cold_start)(&wk->tag);                                     \
    st = BAL_QX(tag##_solve)(&wk->tag, wk->p);                              \
    inaccurate = st == BAL_OK && BAL_QX(tag##_inaccurate)(&wk->tag);        \
    if (st == BAL_OK && !inaccurate) {                                      \
      memcpy(wk->plan + (BAL_QX(N) - hh) * BAL_QX(NU),                      \
             wk->tag.x + BAL_QX(tag##_W_v), hh * BAL_QX(NU) * sizeof(casadi_real)); \
      BAL_QX(feedback)(x, wk->plan + (BAL_QX(N) - hh) * BAL_QX(NU), u_out); \
    }                                                                       \
  }
  BAL_QX(SHRUNK)(BAL_RAPSF_SHRUNK_SOLVE)
#undef BAL_RAPSF_SHRUNK_SOLVE
  wk->shrunk_status = st;
  wk->shrunk_inaccurate = inaccurate;
  return st == BAL_OK && !inaccurate;
}
#endif

int BAL_QX(step)(const casadi_real* x, const casadi_real* u_p, const casadi_real* theta,
                 const casadi_real* s, int falsified, casadi_real* u_out, int* status,
                 BAL_QX(work)* wk) {
  casadi_int i;
  if (!x || !u_p || !theta || !s || !u_out || !status || !wk) {
    if (status) *status = BAL_RAPSF_BAD_INPUT;
    if (x && u_out) BAL_QX(apply_backup)(x, u_out, wk);
    return BAL_RAPSF_BAD_INPUT;
  }
  wk->main_status = BAL_NOT_RUN;
  wk->shrunk_status = BAL_NOT_RUN;
  wk->main_inaccurate = wk->shrunk_inaccurate = 0;
  wk->objective = NAN;
  wk->n_replaced = bal_read_proposal(u_p, wk->u_p, BAL_QX(NU));
  if (falsified || !bal_finite(x, BAL_QX(NX))
      || !bal_finite(theta, BAL_QX(NQ) * BAL_QX(NTH))
      || !bal_finite(s, BAL_QX(NXR) * BAL_QX(NTH))) {
    /* nothing solved: the backup policy; k_inf and the plan are kept (a non-finite θ or s
       is bad input as a non-finite x: review R1, session 15) */
    BAL_QX(apply_backup)(x, u_out, wk);
    *status = falsified ? BAL_RAPSF_FALSIFIED : BAL_RAPSF_BAD_INPUT;
    return *status;
  }
  for (i = 0; i < BAL_QX(NX); ++i) wk->p[BAL_QX(main_P_x0) + i] = x[i];
  for (i = 0; i < BAL_QX(NU); ++i) wk->p[BAL_QX(main_P_u_p) + i] = wk->u_p[i];
  memcpy(wk->p + BAL_QX(main_P_theta), theta,
         BAL_QX(NQ) * BAL_QX(NTH) * sizeof(casadi_real));
  memcpy(wk->p + BAL_QX(main_P_s), s, BAL_QX(NXR) * BAL_QX(NTH) * sizeof(casadi_real));
#if BAL_QX(WARM_START)
  /* RAPSF(warm_start=True): from the previous step's solution after a converged (4.5)
     (k_inf == 0), else cold; the Python controller's rule */
  if (wk->have_plan && wk->k_inf == 0) BAL_QX(main_warm_start)(&wk->main);
  else BAL_QX(main_cold_start)(&wk->main);
#else
  /* every solve starts cold, as the Python controller's */
  BAL_QX(main_cold_start)(&wk->main);
#endif
  wk->main_status = BAL_QX(main_solve)(&wk->main, wk->p);
  /* a BAL_OK that stopped at the solver's acceptable level (IPOPT's
     Solved_To_Acceptable_Level, <P>_inaccurate) is the backend's optimal_inaccurate, which
     RAPSF handles as infeasible (only an optimal solve is used): so does the C */
  wk->main_inaccurate = wk->main_status == BAL_OK && BAL_QX(main_inaccurate)(&wk->main);
  if (wk->main_status == BAL_OK && !wk->main_inaccurate) {
    memcpy(wk->plan, wk->main.x + BAL_QX(main_W_v), sizeof(wk->plan));
    wk->have_plan = 1;
    wk->k_inf = 0;
    wk->objective = wk->main.f;
    BAL_QX(feedback)(x, wk->plan, u_out);
    *status = BAL_RAPSF_OK;
    return *status;
  }
  wk->k_inf += 1;
  if (wk->k_inf <= BAL_QX(N) - 1 && wk->have_plan) {
#if BAL_QX(SHRINKING)
    if (BAL_QX(solve_shrunk)(wk, BAL_QX(N) - wk->k_inf, x, u_out)) {
      *status = BAL_RAPSF_SHRUNK_HORIZON;
      return *status;
    }
#endif
    BAL_QX(feedback)(x, wk->plan + wk->k_inf * BAL_QX(NU), u_out);
    *status = BAL_RAPSF_STORED_PLAN;
  } else {
    BAL_QX(apply_backup)(x, u_out, wk);
    *status = BAL_RAPSF_BACKUP;
  }
  return *status;
}

BAL_QX(main_work)* BAL_QX(main_problem)(BAL_QX(work)* wk) { return &wk->main; }
int BAL_QX(solve_status)(const BAL_QX(work)* wk) { return wk->main_status; }
int BAL_QX(shrunk_status)(const BAL_QX(work)* wk) { return wk->shrunk_status; }
int BAL_QX(inaccurate)(const BAL_QX(work)* wk, int which) {
  return which ? wk->shrunk_inaccurate : wk->main_inaccurate;
}
int BAL_QX(k_inf)(const BAL_QX(work)* wk) { return wk->k_inf; }
casadi_real BAL_QX(objective)(const BAL_QX(work)* wk) { return wk->objective; }
int BAL_QX(proposal_replaced)(const BAL_QX(work)* wk) { return wk->n_replaced; }
