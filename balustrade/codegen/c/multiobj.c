/* bal/multiobj.c: the Algorithm 6.4 control step Q = BAL_STEP (bal/multiobj.h) with the
 * fallbacks of balustrade.control.multiobjective. Included by the generated <name>.c after
 * the problems Q_slack (5.15) and Q_problem (6.15). From <name>_config.h: Q_NX, Q_NU, Q_N,
 * Q_N_XI, the box U, the feedback Q_K (NU x NX, column-major), Q_RHO, Q_BOUND_TOL,
 * Q_DECREASE_TOL (control.multiobjective.DECREASE_TOL, the threshold of (6.15g) on the
 * polished slacks), Q_XI_SUM (the running-sum form of the slacks), Q_CANDIDATE_DUALS and
 * Q_CANDIDATE_SECOND (the opt-in starts of MultiobjectivePCBFController(candidate_duals=,
 * candidate_second=), session 14), and the
 * emitted functions Q_post_slack / Q_post_problem (polished slacks, h~) and Q_cand (the
 * candidate (6.14)).
 */
#include <math.h>
#include <stdlib.h>
#include <string.h>

#include "step_common.c"

static const casadi_real BAL_QX(u_lb)[BAL_QX(NU)] = BAL_QX(U_LB);
static const casadi_real BAL_QX(u_ub)[BAL_QX(NU)] = BAL_QX(U_UB);
static const casadi_real BAL_QX(kappa)[BAL_QX(NU) * BAL_QX(NX)] = BAL_QX(K);

BAL_DEFINE_PAIR_INIT_FINALIZE(BAL_QX, slack, problem)

BAL_DEFINE_ALLOC_FREE(BAL_QX)

#include "tube_common.c"

void BAL_QX(reset)(BAL_QX(work)* wk) {
  BAL_QX(slack_cold_start)(&wk->slack);
  BAL_QX(problem_cold_start)(&wk->problem);
  wk->have_cand = wk->have_problem = wk->n_replaced = wk->recovered = 0;
  wk->cand_exact = 1;
  wk->slack_status = wk->problem_status = BAL_NOT_RUN;
  wk->h_prev = NAN;
  wk->values[0] = wk->values[1] = wk->values[2] = wk->values[3] = NAN;
}

/* polished slacks and h~ of a solution w with value f (Q_post_slack / Q_post_problem);
   0 on success */
typedef int (*BAL_QX(post_fn))(const casadi_real**, casadi_real**, casadi_int*, casadi_real*,
                               int);
static int BAL_QX(polish)(BAL_QX(work)* wk, BAL_QX(post_fn) post, const casadi_real* w,
                          const casadi_real* f) {
  wk->arg[0] = w;
  wk->arg[1] = f;
  wk->res[0] = wk->xi;
  wk->res[1] = &wk->xi_N;
  wk->res[2] = &wk->h_r;
  wk->res[3] = &wk->h_tilde;
  return post(wk->arg, wk->res, wk->iw, wk->w, 0);
}

#define BAL_MO_COPY(var, src, n)                                              \
  memcpy(dst + BAL_QX(problem_W_##var), (src), (n) * sizeof(casadi_real));

/* the candidate (6.14) as a start of (6.15) in dst (P_NW values): its z, v, xi, xi_N (and
   the running sums of its slacks in the running-sum form of (6.15g)) over the rest of
   what dst holds (Python's _candidate_start) */
static void BAL_QX(candidate_into)(const BAL_QX(work)* wk, casadi_real* dst) {
  BAL_MO_COPY(z, wk->cz, BAL_QX(NX) * (BAL_QX(N) + 1))
  BAL_MO_COPY(v, wk->cv, BAL_QX(NU) * BAL_QX(N))
  BAL_MO_COPY(xi, wk->cxi, BAL_QX(N_XI))
  BAL_MO_COPY(xi_N, &wk->cxi_N, 1)
#if BAL_QX(XI_SUM)
  /* the running sums of the candidate's slacks (the running-sum form of (6.15g)) */
  {
    casadi_int i, j, nr = BAL_QX(N_XI) / BAL_QX(N);
    casadi_real acc = 0;
    for (i = 0; i < BAL_QX(N); ++i) {
      for (j = 0; j < nr; ++j) acc += wk->cxi[i * nr + j];
      dst[BAL_QX(problem_W_xi_sum) + i] = acc;
    }
  }
#endif
}

int BAL_QX(step)(const casadi_real* x, const casadi_real* u_p, casadi_real* u_out,
                 int* status, BAL_QX(work)* wk) {
  casadi_int i;
  int lead;
  casadi_real bound;
  const casadi_real *z, *v, *second;
  if (!x || !u_p || !u_out || !status || !wk) {
    if (status) *status = BAL_MULTIOBJ_BAD_INPUT;
    return BAL_MULTIOBJ_BAD_INPUT;
  }
  wk->slack_status = wk->problem_status = BAL_NOT_RUN;
  wk->values[0] = wk->values[1] = wk->values[2] = wk->values[3] = NAN;
  wk->n_replaced = bal_read_proposal(u_p, wk->u_p, BAL_QX(NU));
  if (!bal_finite(x, BAL_QX(NX))) {
    wk->slack_status = wk->problem_status = BAL_BAD_INPUT;
    bal_clip(wk->u_p, BAL_QX(u_lb), BAL_QX(u_ub), u_out, BAL_QX(NU));
    *status = BAL_MULTIOBJ_BAD_INPUT;
    return *status;
  }
  if (!wk->have_cand) {
    /* initialization from (5.15) */
    for (i = 0; i < BAL_QX(NX); ++i) wk->p_slack[BAL_QX(slack_P_x0) + i] = x[i];
    /* a recovery step: the attempt Q_SLACK_LEAD leads (0: none) */
    wk->slack_status = BAL_QX(slack_solve_lead)(&wk->slack, wk->p_slack, 0,
                                                BAL_QX(SLACK_LEAD));
    if (wk->slack_status == BAL_OK &&
        BAL_QX(polish)(wk, BAL_QX(post_slack), wk->slack.x, &wk->slack.f)) {
      wk->slack_status = BAL_EVAL_ERROR;
    }
    if (wk->slack_status != BAL_OK) {
      bal_clip(wk->u_p, BAL_QX(u_lb), BAL_QX(u_ub), u_out, BAL_QX(NU));
      *status = BAL_MULTIOBJ_INIT_FAILED;
      return *status;
    }
    BAL_QX(slack_warm_start)(&wk->slack);
    memcpy(wk->cz, wk->slack.x + BAL_QX(slack_W_z), sizeof(wk->cz));
    memcpy(wk->cv, wk->slack.x + BAL_QX(slack_W_v), sizeof(wk->cv));
    memcpy(wk->cxi, wk->xi, sizeof(wk->cxi));
    wk->cxi_N = wk->xi_N;
    wk->ch = wk->h_prev = wk->h_tilde;
    wk->have_cand = 1;
  }
  /* (6.15) with the decrease bound (6.15g) */
  bound = (1.0 - BAL_QX(RHO)) * wk->ch + BAL_QX(RHO) * wk->h_prev;
  bound += BAL_QX(BOUND_TOL) * fmax(1.0, fabs(bound));
  wk->values[0] = wk->ch;
  wk->values[1] = bound;
  for (i = 0; i < BAL_QX(NX); ++i) wk->p_problem[BAL_QX(problem_P_x0) + i] = x[i];
  for (i = 0; i < BAL_QX(NU); ++i) wk->p_problem[BAL_QX(problem_P_u_p) + i] = wk->u_p[i];
  wk->p_problem[BAL_QX(problem_P_bound)] = bound;
  /* the first (6.15) until one converges is a recovery solve: the attempt Q_PROBLEM_LEAD
     leads (0: none); the ones after it start from the candidate as well until one converges
     (balustrade.control.multiobjective.MultiobjectivePCBFController.recovering) */
  lead = (BAL_QX(PROBLEM_LEAD) > 0 && !wk->have_problem) ? BAL_QX(PROBLEM_LEAD) : 0;
  if (!wk->have_problem || wk->recovered || BAL_QX(CANDIDATE_DUALS)) {
    if (!wk->have_problem || wk->recovered) {
      /* before its first success and after a recovery solve until one converges: from
         the candidate, the rest cold */
      BAL_QX(problem_cold_start)(&wk->problem);
    } else {
      /* an ordinary step (Q_CANDIDATE_DUALS): from the candidate with the multipliers of
         the last converged (6.15), which P_warm_start left in lam_x0/lam_g0; the rest of
         the primal cold (Python's duals_from, MultiobjectivePCBFController.candidate_duals) */
      memcpy(wk->problem.x0, BAL_QX(problem_init_x), sizeof(wk->problem.x0));
    }
    BAL_QX(candidate_into)(wk, wk->problem.x0);
    second = 0;
  } else if (BAL_QX(CANDIDATE_SECOND)) {
    /* an ordinary step (Q_CANDIDATE_SECOND): from the last converged (6.15), and if that
       attempt fails from the candidate with its multipliers before the cold retries
       (Python's second_start/second_duals, candidate_second) */
    memcpy(wk->cstart, BAL_QX(problem_init_x), sizeof(wk->cstart));
    BAL_QX(candidate_into)(wk, wk->cstart);
    second = wk->cstart;
  } else {
    second = 0;
  }
  wk->problem.second_duals = second != 0;
  wk->problem_status = BAL_QX(problem_solve_lead)(&wk->problem, wk->p_problem, second, lead);
  wk->problem.second_duals = 0;
  /* from the candidate again until a (6.15) converges after the recovery solve (Python's
     _recovered: its warm start is then the candidate's, never the interior-point point) */
  wk->recovered = lead > 0 || (wk->recovered && wk->problem_status != BAL_OK);
  /* a (6.15) answered by the recovery attempt's solver (as a retry) is followed by a start
     from the candidate too: its interior-point point stops the next SQP after one costly
     QP (Python's _answered_by_lead; docs/vehicles.md, "session 13: Algorithm 6.4's worst
     steps") */
  if (BAL_QX(PROBLEM_LEAD) > 0 && wk->problem_status == BAL_OK &&
      BAL_QX(problem_solvers)[wk->problem.which].eval ==
          BAL_QX(problem_solvers)[BAL_QX(PROBLEM_LEAD)].eval) {
    wk->recovered = 1;
  }
  if (wk->problem_status == BAL_OK &&
      BAL_QX(polish)(wk, BAL_QX(post_problem), wk->problem.x, &wk->problem.f)) {
    wk->problem_status = BAL_EVAL_ERROR;
  }
  if (wk->problem_status == BAL_OK) {
    BAL_QX(problem_warm_start)(&wk->problem);
    wk->have_problem = 1;
  }
  /* (6.15g) on the polished slacks: a plan needing more than the bound is no feasible
     point of (6.15) (balustrade.control.multiobjective._meets_decrease) */
  if (wk->problem_status == BAL_OK &&
      !(wk->h_tilde <= bound + BAL_QX(DECREASE_TOL) * fmax(1.0, fabs(bound)))) {
    z = wk->cz;
    v = wk->cv;
    memcpy(wk->xi, wk->cxi, sizeof(wk->xi));
    wk->values[3] = wk->h_tilde; /* values["h_tilde_rejected"] in Python */
    wk->h_prev = wk->ch;
    *status = BAL_MULTIOBJ_ABOVE_BOUND;
  } else if (wk->problem_status == BAL_OK) {
    z = wk->problem.x + BAL_QX(problem_W_z);
    v = wk->problem.x + BAL_QX(problem_W_v);
    wk->h_prev = wk->h_tilde;
    *status = BAL_MULTIOBJ_OK;
  } else {
    z = wk->cz;
    v = wk->cv;
    memcpy(wk->xi, wk->cxi, sizeof(wk->xi));
    wk->h_prev = wk->ch;
    *status = BAL_MULTIOBJ_WARM_START;
  }
  wk->values[2] = wk->h_prev;
  BAL_QX(applied)(x, z, v, u_out);
  BAL_QX(make_candidate)(wk, z, v, wk->xi);
  return *status;
}

#undef BAL_MO_COPY

BAL_DEFINE_PAIR_ACCESSORS(BAL_QX, slack, problem, slack_problem, main_problem)
void BAL_QX(values)(const BAL_QX(work)* wk, casadi_real* out) {
  out[0] = wk->values[0];
  out[1] = wk->values[1];
  out[2] = wk->values[2];
  out[3] = wk->values[3];
}
int BAL_QX(proposal_replaced)(const BAL_QX(work)* wk) { return wk->n_replaced; }
int BAL_QX(candidate_exact)(const BAL_QX(work)* wk) { return wk->cand_exact; }
