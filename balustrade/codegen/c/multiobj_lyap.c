/* bal/multiobj_lyap.c: the Algorithm 6.3 control step Q = BAL_STEP (bal/multiobj_lyap.h)
 * with the fallbacks of balustrade.control.multiobjective.MultiobjectiveLyapunovController.
 * Included by the generated <name>.c after the problems Q_first (6.3) and Q_problem (6.10).
 * From <name>_config.h: Q_NX, Q_NU, Q_N, the box U, Q_BOUND_TOL, Q_XF_TOL, Q_ADM_TOL and
 * the emitted functions Q_switch (xi_c, xi_f, their V, the X_f and (6.3b-g) margins),
 * Q_bound (the right side of (6.3h) and the rollout) and Q_V ((6.2)).
 */
#include <math.h>
#include <stdlib.h>
#include <string.h>

#include "step_common.c"

static const casadi_real BAL_QX(u_lb)[BAL_QX(NU)] = BAL_QX(U_LB);
static const casadi_real BAL_QX(u_ub)[BAL_QX(NU)] = BAL_QX(U_UB);

BAL_DEFINE_PAIR_INIT_FINALIZE(BAL_QX, first, problem)

BAL_DEFINE_ALLOC_FREE(BAL_QX)

void BAL_QX(reset)(BAL_QX(work)* wk) {
  BAL_QX(first_cold_start)(&wk->first);
  BAL_QX(problem_cold_start)(&wk->problem);
  wk->have_prev = wk->n_replaced = 0;
  wk->first_status = wk->problem_status = BAL_NOT_RUN;
  wk->values[0] = wk->values[1] = wk->values[2] = NAN;
}

/* the switching rule (6.6)/(6.7): u~ := xi_f or xi_c; returns the evaluation's status */
static int BAL_QX(switch_rule)(BAL_QX(work)* wk, const casadi_real* x) {
  casadi_real V_c, V_f, m_xf, m_adm;
  int use_f;
  wk->arg[0] = x;
  wk->arg[1] = wk->x_prev;
  wk->arg[2] = wk->u_prev;
  wk->arg[3] = wk->v_prev;
  wk->res[0] = wk->cand_c;
  wk->res[1] = wk->cand_f;
  wk->res[2] = &V_c;
  wk->res[3] = &V_f;
  wk->res[4] = &m_xf;
  wk->res[5] = &m_adm;
  if (BAL_QX(switch)(wk->arg, wk->res, wk->iw, wk->w, 0)) return -1;
  use_f = m_xf <= BAL_QX(XF_TOL) && V_f <= V_c && m_adm <= BAL_QX(ADM_TOL);
  memcpy(wk->u_tilde, use_f ? wk->cand_f : wk->cand_c, sizeof(wk->u_tilde));
  wk->values[0] = use_f ? 1.0 : 0.0;
  return 0;
}

int BAL_QX(step)(const casadi_real* x, const casadi_real* u_p, casadi_real* u_out,
                 int* status, BAL_QX(work)* wk) {
  casadi_int i;
  casadi_real bound, V;
  const casadi_real* v;
  if (!x || !u_p || !u_out || !status || !wk) {
    if (status) *status = BAL_MO_LYAP_BAD_INPUT;
    return BAL_MO_LYAP_BAD_INPUT;
  }
  wk->first_status = wk->problem_status = BAL_NOT_RUN;
  wk->values[0] = wk->values[1] = wk->values[2] = NAN;
  wk->n_replaced = bal_read_proposal(u_p, wk->u_p, BAL_QX(NU));
  if (!bal_finite(x, BAL_QX(NX))) {
    wk->first_status = wk->problem_status = BAL_BAD_INPUT;
    bal_clip(wk->u_p, BAL_QX(u_lb), BAL_QX(u_ub), u_out, BAL_QX(NU));
    *status = BAL_MO_LYAP_BAD_INPUT;
    return *status;
  }
  if (!wk->have_prev) {
    /* Algorithm 6.3 step 2: (6.3) without (6.3h), from a cold start */
    for (i = 0; i < BAL_QX(NX); ++i) wk->p_first[BAL_QX(first_P_x0) + i] = x[i];
    for (i = 0; i < BAL_QX(NU); ++i) wk->p_first[BAL_QX(first_P_u_p) + i] = wk->u_p[i];
    BAL_QX(first_cold_start)(&wk->first);
    wk->first_status = BAL_QX(first_solve)(&wk->first, wk->p_first);
    if (wk->first_status != BAL_OK) {
      bal_clip(wk->u_p, BAL_QX(u_lb), BAL_QX(u_ub), u_out, BAL_QX(NU));
      *status = BAL_MO_LYAP_INIT_FAILED;
      return *status;
    }
    memcpy(wk->u_tilde, wk->first.x + BAL_QX(first_W_v), sizeof(wk->u_tilde));
    wk->values[0] = 0.0;
  } else if (BAL_QX(switch_rule)(wk, x)) {
    wk->have_prev = 0; /* cannot happen (SX functions): start again next step */
    bal_clip(wk->u_p, BAL_QX(u_lb), BAL_QX(u_ub), u_out, BAL_QX(NU));
    *status = BAL_MO_LYAP_INIT_FAILED;
    return *status;
  }
  /* the bound of (6.3h) and the warm start (v, z) = (u~, rollout) */
  wk->arg[0] = x;
  wk->arg[1] = wk->u_tilde;
  wk->res[0] = &bound;
  wk->res[1] = wk->z_tilde;
  if (BAL_QX(bound)(wk->arg, wk->res, wk->iw, wk->w, 0)) bound = NAN;
  bound += BAL_QX(BOUND_TOL) * fmax(1.0, fabs(bound));
  wk->values[1] = bound;
  for (i = 0; i < BAL_QX(NX); ++i) wk->p_problem[BAL_QX(problem_P_x0) + i] = x[i];
  for (i = 0; i < BAL_QX(NU); ++i) wk->p_problem[BAL_QX(problem_P_u_p) + i] = wk->u_p[i];
  wk->p_problem[BAL_QX(problem_P_bound)] = bound;
  BAL_QX(problem_cold_start)(&wk->problem);
  memcpy(wk->problem.x0 + BAL_QX(problem_W_v), wk->u_tilde, sizeof(wk->u_tilde));
  memcpy(wk->problem.x0 + BAL_QX(problem_W_z), wk->z_tilde, sizeof(wk->z_tilde));
  wk->problem_status = BAL_QX(problem_solve)(&wk->problem, wk->p_problem);
  if (wk->problem_status == BAL_OK) {
    v = wk->problem.x + BAL_QX(problem_W_v);
    *status = BAL_MO_LYAP_OK;
  } else {
    v = wk->u_tilde;
    *status = BAL_MO_LYAP_WARM_START;
  }
  wk->arg[0] = x;
  wk->arg[1] = v;
  wk->res[0] = &V;
  if (BAL_QX(V)(wk->arg, wk->res, wk->iw, wk->w, 0)) V = NAN;
  wk->values[2] = V;
  for (i = 0; i < BAL_QX(NU); ++i) u_out[i] = v[i];
  memcpy(wk->x_prev, x, sizeof(wk->x_prev));
  memcpy(wk->u_prev, u_out, sizeof(wk->u_prev));
  memmove(wk->v_prev, v, sizeof(wk->v_prev));
  wk->have_prev = 1;
  return *status;
}

BAL_DEFINE_PAIR_ACCESSORS(BAL_QX, first, problem, init_problem, main_problem)
void BAL_QX(values)(const BAL_QX(work)* wk, casadi_real* out) {
  out[0] = wk->values[0];
  out[1] = wk->values[1];
  out[2] = wk->values[2];
}
int BAL_QX(proposal_replaced)(const BAL_QX(work)* wk) { return wk->n_replaced; }
