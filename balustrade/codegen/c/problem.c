/* bal/problem.c: one emitted problem P = BAL_PROBLEM: warm starts, the solve with its
 * cold-start retries and the BAL_FEASIBLE rule (mirroring balustrade's CasADi backend).
 * Included once per problem by the generated <name>.c, after <name>.h. The numbers come
 * from <name>_config.h: bounds P_LBX/P_UBX/P_LBG/P_UBG, initial point P_INIT_X, the
 * tolerances P_TOL_PR, P_TOL_DU, P_ACCEPT_TOL, the objective scale P_F_SCALE, the
 * iteration budget P_BUDGET (0: none; else a first attempt that stops without converging is
 * BAL_TRUNCATED, never retried), P_SECOND_SOLVER (the attempt whose solver runs from a
 * second start, P_solve_from; 0: the first solver), and P_SOLVERS(X), the CasADi solvers of the
 * first attempt and of each retry (the same function twice shares its memory), P_REPORTS,
 * per attempt 1 if its solver returns its own verdict (the interior-point
 * solver: BAL_OK when it converged; P_inaccurate 1 when it stopped at its acceptable
 * level, P_RETURN_STATUS_FNS/P_ACCEPTABLE_STOP)
 * instead of being judged by P_TOL_PR/P_TOL_DU. P_kkt
 * evaluates the solver's own convergence measures at a point.
 */
#include <math.h>
#include <stdlib.h>
#include <string.h>

static const casadi_real BAL_PX(lbx)[BAL_PX(NW)] = BAL_PX(LBX);
static const casadi_real BAL_PX(ubx)[BAL_PX(NW)] = BAL_PX(UBX);
static const casadi_real BAL_PX(lbg)[BAL_PX(NG1)] = BAL_PX(LBG);
static const casadi_real BAL_PX(ubg)[BAL_PX(NG1)] = BAL_PX(UBG);
static const casadi_real BAL_PX(init_x)[BAL_PX(NW)] = BAL_PX(INIT_X);
/* solver of attempt k: k = 0 from the warm start, k >= 1 the k-th cold-start retry */
static const bal_casadi_fn BAL_PX(solvers)[BAL_PX(N_SOLVERS)] = {BAL_PX(SOLVERS)(BAL_CASADI_FN)};
/* 1 if the solver of attempt k returns its own verdict (0: converged; the interior-point
   solver, whose convergence test is on its internally scaled problem), else its KKT residuals decide */
static const int BAL_PX(reports)[BAL_PX(N_SOLVERS)] = BAL_PX(REPORTS);
/* the solver of attempt k's own return status of its last run on a memory (0: the solver
   does not keep one), and the value of that status meaning "stopped at the acceptable
   level" (IPOPT's Solved_To_Acceptable_Level, which its generated C returns as converged:
   backends.emittable.ACCEPTABLE_STOP) */
typedef int (*BAL_PX(return_status_fn))(int mem);
static const BAL_PX(return_status_fn) BAL_PX(return_status)[BAL_PX(N_SOLVERS)] =
    BAL_PX(RETURN_STATUS_FNS);
static const int BAL_PX(acceptable_stop)[BAL_PX(N_SOLVERS)] = BAL_PX(ACCEPTABLE_STOP);

/* the first attempt that uses the solver of attempt k (its memory is shared) */
static int BAL_PX(first_use)(int k) {
  int j;
  for (j = 0; j < k; ++j) {
    if (BAL_PX(solvers)[j].eval == BAL_PX(solvers)[k].eval) return j;
  }
  return k;
}

/* release the memory of the solvers of attempts n - 1, ..., 0 */
static void BAL_PX(release_solvers)(BAL_PX(work)* wk, int n) {
  int k;
  for (k = n - 1; k >= 0; --k) {
    if (BAL_PX(first_use)(k) == k) {
      BAL_PX(solvers)[k].release(wk->mem[k]);
      BAL_PX(solvers)[k].decref();
    }
  }
}

int BAL_PX(init)(BAL_PX(work)* wk) {
  int k, j;
  wk->ready = 0;
  for (k = 0; k < BAL_PX(N_SOLVERS); ++k) {
    j = BAL_PX(first_use)(k);
    if (j < k) { /* the same function again: reuse its memory */
      wk->mem[k] = wk->mem[j];
      continue;
    }
    BAL_PX(solvers)[k].incref();
    wk->mem[k] = BAL_PX(solvers)[k].checkout();
    if (wk->mem[k] < 0) {
      BAL_PX(solvers)[k].decref();
      BAL_PX(release_solvers)(wk, k);
      return -1;
    }
  }
  BAL_PX(kkt_incref)();
  wk->kmem = BAL_PX(kkt_checkout)();
  if (wk->kmem < 0) {
    BAL_PX(kkt_decref)();
    BAL_PX(release_solvers)(wk, BAL_PX(N_SOLVERS));
    return -1;
  }
  BAL_PX(cold_start)(wk);
  wk->second_duals = 0;
  wk->ready = 1;
  return 0;
}

void BAL_PX(finalize)(BAL_PX(work)* wk) {
  if (!wk->ready) return;
  BAL_PX(kkt_release)(wk->kmem);
  BAL_PX(kkt_decref)();
  BAL_PX(release_solvers)(wk, BAL_PX(N_SOLVERS));
  wk->ready = 0;
}

BAL_DEFINE_ALLOC_FREE(BAL_PX)

void BAL_PX(cold_start)(BAL_PX(work)* wk) {
  memcpy(wk->x0, BAL_PX(init_x), sizeof(wk->x0));
  memset(wk->lam_x0, 0, sizeof(wk->lam_x0));
  memset(wk->lam_g0, 0, sizeof(wk->lam_g0));
}

void BAL_PX(warm_start)(BAL_PX(work)* wk) {
  memcpy(wk->x0, wk->x, sizeof(wk->x0));
  memcpy(wk->lam_x0, wk->lam_x, sizeof(wk->lam_x0));
  memcpy(wk->lam_g0, wk->lam_g, sizeof(wk->lam_g0));
}

void BAL_PX(warm_start_primal)(BAL_PX(work)* wk) {
  BAL_PX(cold_start)(wk);
  memcpy(wk->x0, wk->x, BAL_PX(N_USER) * sizeof(casadi_real));
}

/* One solver run of the solver of attempt `which`: from the primal `start` with zero
   multipliers (the warm ones when wk->second_duals) if not NULL, else which = 0 from the
   warm start in wk and which >= 1 (a retry) from a cold start. */
static int BAL_PX(attempt)(BAL_PX(work)* wk, const casadi_real* p, int which,
                           const casadi_real* start) {
  casadi_int i;
  int flag;
  wk->arg[0] = start ? start : which ? BAL_PX(init_x) : wk->x0;
  wk->arg[1] = p;
  wk->arg[2] = BAL_PX(lbx);
  wk->arg[3] = BAL_PX(ubx);
  wk->arg[4] = BAL_PX(lbg);
  wk->arg[5] = BAL_PX(ubg);
  /* 0: zero multipliers; a second start keeps the warm ones when wk->second_duals */
  wk->arg[6] = (start ? wk->second_duals : !which) ? wk->lam_x0 : 0;
  wk->arg[7] = (start ? wk->second_duals : !which) ? wk->lam_g0 : 0;
  wk->res[0] = wk->x;
  wk->res[1] = &wk->f;
  wk->res[2] = wk->g;
  wk->res[3] = wk->lam_x;
  wk->res[4] = wk->lam_g;
  wk->res[5] = wk->lam_p;
  wk->attempts++;
  wk->which = which;
  wk->inaccurate = 0;
  if (which < 0 || which >= BAL_PX(N_SOLVERS)) return BAL_EVAL_ERROR;
  flag = BAL_PX(solvers)[which].eval(wk->arg, wk->res, wk->iw, wk->w, wk->mem[which]);
  if (flag && !BAL_PX(reports)[which]) return BAL_EVAL_ERROR;
  wk->f /= BAL_PX(F_SCALE); /* the declared objective (casadi_backend.objective_scale) */
  wk->karg[0] = wk->x;
  wk->karg[1] = p;
  wk->karg[2] = wk->lam_x;
  wk->karg[3] = wk->lam_g;
  wk->kres[0] = &wk->pr_inf;
  wk->kres[1] = &wk->du_inf;
  wk->kres[2] = &wk->feas;
  if (BAL_PX(kkt)(wk->karg, wk->kres, wk->kiw, wk->kw, wk->kmem)) return BAL_EVAL_ERROR;
  if (!isfinite(wk->f) || !isfinite(wk->pr_inf) || !isfinite(wk->du_inf)) return BAL_NONFINITE;
  for (i = 0; i < BAL_PX(NW); ++i) {
    if (!isfinite(wk->x[i])) return BAL_NONFINITE;
  }
  if (BAL_PX(reports)[which]) {
    if (!flag) { /* the solver's own test passed, as the backend reads it; a stop at its
                    acceptable level is the backend's optimal_inaccurate: flagged */
      wk->inaccurate = BAL_PX(return_status)[which] &&
          BAL_PX(return_status)[which](wk->mem[which]) == BAL_PX(acceptable_stop)[which];
      return BAL_OK;
    }
  } else if (wk->pr_inf < BAL_PX(TOL_PR) && wk->du_inf < BAL_PX(TOL_DU)) {
    return BAL_OK;
  }
  return wk->feas <= BAL_PX(ACCEPT_TOL) ? BAL_FEASIBLE : BAL_NOT_CONVERGED;
}

/* 1 if the P_NP parameters are all finite (NaN compares false: a NaN parameter would
   make the residual tests pass), else 0 */
static int BAL_PX(finite_params)(const casadi_real* p) {
  casadi_int i;
  for (i = 0; i < BAL_PX(NP); ++i) {
    if (!isfinite(p[i])) return 0;
  }
  return 1;
}

/* 1 if the n values are all finite, else 0 */
static int BAL_PX(finite_vec)(const casadi_real* v, casadi_int n) {
  casadi_int i;
  for (i = 0; i < n; ++i) {
    if (!isfinite(v[i])) return 0;
  }
  return 1;
}

/* keep (save = 1) or restore (save = 0) the point of a BAL_FEASIBLE attempt */
static void BAL_PX(feasible_copy)(BAL_PX(work)* wk, int save) {
  if (save) {
    memcpy(wk->kx, wk->x, sizeof(wk->kx));
    memcpy(wk->klam_x, wk->lam_x, sizeof(wk->klam_x));
    memcpy(wk->klam_g, wk->lam_g, sizeof(wk->klam_g));
    memcpy(wk->kg, wk->g, sizeof(wk->kg));
    wk->kf = wk->f;
    wk->kpr_inf = wk->pr_inf;
    wk->kdu_inf = wk->du_inf;
    wk->kfeas = wk->feas;
  } else {
    memcpy(wk->x, wk->kx, sizeof(wk->kx));
    memcpy(wk->lam_x, wk->klam_x, sizeof(wk->klam_x));
    memcpy(wk->lam_g, wk->klam_g, sizeof(wk->klam_g));
    memcpy(wk->g, wk->kg, sizeof(wk->kg));
    wk->f = wk->kf;
    wk->pr_inf = wk->kpr_inf;
    wk->du_inf = wk->kdu_inf;
    wk->feas = wk->kfeas;
  }
}

/* 1 if the warm start in wk is the cold start (P_INIT_X, zero multipliers), else 0 */
static int BAL_PX(is_cold)(const BAL_PX(work)* wk) {
  casadi_int i;
  for (i = 0; i < BAL_PX(NW); ++i) {
    if (wk->x0[i] != BAL_PX(init_x)[i] || wk->lam_x0[i] != 0) return 0;
  }
  for (i = 0; i < BAL_PX(NG); ++i) {
    if (wk->lam_g0[i] != 0) return 0;
  }
  return 1;
}

/* 1 if retry `which` (a cold start) would repeat an attempt that already ran in this
   P_solve: the same solver function from the same start (an earlier retry, or the first
   attempt when it started cold). The solvers are deterministic, so it would repeat that
   attempt's run; skipped, as balustrade's backend does (casadi_backend._same_start: the
   cold fatrop retry of structured-ip after a cold first attempt). */
static int BAL_PX(ran_before)(int which, int first_cold) {
  int j;
  for (j = first_cold ? 0 : 1; j < which; ++j) {
    if (BAL_PX(solvers)[j].eval == BAL_PX(solvers)[which].eval) return 1;
  }
  return 0;
}

int BAL_PX(solve)(BAL_PX(work)* wk, const casadi_real* p) {
  return BAL_PX(solve_from)(wk, p, 0);
}

int BAL_PX(solve_from)(BAL_PX(work)* wk, const casadi_real* p, const casadi_real* second) {
  return BAL_PX(solve_lead)(wk, p, second, 0);
}

/* 1 if retry `which` runs the solver of the lead attempt (lead > 0), which already ran
   cold in this P_solve_lead: skipped (casadi_backend: the lead is in `ran`) */
static int BAL_PX(is_lead)(int which, int lead) {
  return lead > 0 && BAL_PX(solvers)[which].eval == BAL_PX(solvers)[lead].eval;
}

int BAL_PX(solve_lead)(BAL_PX(work)* wk, const casadi_real* p, const casadi_real* second,
                       int lead) {
  int first, first_cold, status, which, have_feasible = 0;
  casadi_int i;
  if (!wk || !wk->ready) return BAL_EVAL_ERROR;
  wk->attempts = 0;
  wk->inaccurate = 0;
  if ((BAL_PX(NP) > 0 && !p) || (p && !BAL_PX(finite_params)(p))) {
    /* refuse before any solver runs; the outputs say "no solution" */
    for (i = 0; i < BAL_PX(NW); ++i) wk->x[i] = NAN;
    wk->f = wk->pr_inf = wk->du_inf = wk->feas = NAN;
    return BAL_BAD_INPUT;
  }
  /* a non-finite warm start (P_warm_start copies wk->x as it is) -> the cold start, as
     CasadiCompiled._initial_guess does for a non-finite Solution (initial values, zero
     multipliers); a non-finite second start is ignored (a NaN start can keep a solver
     from returning) */
  if (!BAL_PX(finite_vec)(wk->x0, BAL_PX(NW)) || !BAL_PX(finite_vec)(wk->lam_x0, BAL_PX(NW)) ||
      !BAL_PX(finite_vec)(wk->lam_g0, BAL_PX(NG))) {
    BAL_PX(cold_start)(wk);
  }
  if (second && !BAL_PX(finite_vec)(second, BAL_PX(NW))) second = 0;
  /* a recovery step (backends.recovery): retry `lead` first, from its cold start; its
     status is the first attempt's (CasadiCompiled.solve's lead) */
  if (BAL_PX(BUDGET) > 0 || lead <= 0 || lead >= BAL_PX(N_SOLVERS)) lead = 0;
  if (lead) {
    first = BAL_PX(attempt)(wk, p, lead, 0);
    if (first == BAL_OK) return first;
    if (first == BAL_FEASIBLE) {
      BAL_PX(feasible_copy)(wk, 1);
      have_feasible = 1;
    }
    status = BAL_PX(attempt)(wk, p, 0, 0);
    if (status == BAL_OK) return status;
  } else {
    first = status = BAL_PX(attempt)(wk, p, 0, 0);
    if (first == BAL_OK) return first;
  }
#if BAL_PX(BUDGET) > 0
  /* stopped by the iteration budget (the budgeted SQP has no other way to stop without
     converging: backends.targets.BUDGET_COMPANIONS): truncated, its iterate and residuals
     kept in wk, no retry and no rescue (the time bound holds), as the backend's
     max_iterations with Solution.truncated */
  if (first == BAL_FEASIBLE || first == BAL_NOT_CONVERGED) return BAL_TRUNCATED;
#endif
  if (status == BAL_FEASIBLE) {
    BAL_PX(feasible_copy)(wk, 1);
    have_feasible = 1;
  }
  first_cold = BAL_PX(is_cold)(wk);
  /* the solver of attempt P_SECOND_SOLVER (0: the first) from `second` before the cold
     retries (CasadiCompiled.solve's second_start, second_solver); then the retries, each
     skipped when it would repeat a cold run (an earlier one, or the lead's) */
  for (which = second ? -1 : 1; which < BAL_PX(N_SOLVERS); ++which) {
    if (which == 0) continue; /* attempt 0 ran above */
    if (which > 0 && (BAL_PX(ran_before)(which, first_cold) || BAL_PX(is_lead)(which, lead))) {
      continue; /* the same run again */
    }
    status = which < 0 ? BAL_PX(attempt)(wk, p, BAL_PX(SECOND_SOLVER), second)
                       : BAL_PX(attempt)(wk, p, which, 0);
    if (status == BAL_OK) return status;
    if (status == BAL_FEASIBLE) {
      BAL_PX(feasible_copy)(wk, 1);
      have_feasible = 1;
    }
  }
  /* nothing converged: the last primal-feasible attempt is reported as BAL_FEASIBLE (safe
     to apply, possibly suboptimal), never the point of a later infeasible attempt;
     otherwise the first attempt's status (wk->x then holds the last attempt) */
  if (have_feasible) {
    BAL_PX(feasible_copy)(wk, 0);
    wk->inaccurate = 0;
    return BAL_FEASIBLE;
  }
  return first;
}

int BAL_PX(attempts)(const BAL_PX(work)* wk) { return wk->attempts; }

int BAL_PX(inaccurate)(const BAL_PX(work)* wk) { return wk->inaccurate; }

int BAL_PX(truncated_feasible)(const BAL_PX(work)* wk, int status) {
  return status == BAL_TRUNCATED && wk->pr_inf <= BAL_PX(TRUNC_TOL);
}

const casadi_real* BAL_PX(primal)(const BAL_PX(work)* wk) { return wk->x; }
casadi_real BAL_PX(value)(const BAL_PX(work)* wk) { return wk->f; }
void BAL_PX(residuals)(const BAL_PX(work)* wk, casadi_real* out) {
  out[0] = wk->pr_inf;
  out[1] = wk->du_inf;
  out[2] = wk->feas;
}
