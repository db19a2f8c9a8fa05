/* bal/grid.h: Algorithm 8.7, the input-grid approximate PCBF filter A = BAL_STEP with rate
 * limits, one call per control step and no solver. Included by the generated <name>.h;
 * A_h and A_h_next (h^(x), h^(f(x, u))) are CasADi-generated.
 *
 * A_step(x, u_p, u_out, h_out, status, work), as balustrade.control.approximate.GridPCBFFilter:
 *   1. candidates C: u_{k-1} + each of the A_M offsets (itertools.product order), clipped to
 *      the box U, rounded to 12 decimals, sorted lexicographically, duplicates removed
 *      (numpy.unique(numpy.round(c, 12), axis=0));
 *   2. h^(f(x, c)) for every candidate in one loop (NaN or inf read as +inf), h_out = h^(x);
 *   3. among the candidates with h^(f(x, c)) <= A_RHO h^(x), the first closest to u_p in
 *      the norm scaled by the input ranges A_SCALE: BAL_GRID_OK;
 *      none                         -> the first minimizer of h^(f(x, .)) on C
 *                                                            BAL_GRID_NO_DECREASE
 *      x NaN/inf, NULL args         -> u_{k-1} unchanged     BAL_GRID_BAD_INPUT
 *      u_p NaN/inf (x finite)       -> those entries read as 0, the step runs as usual
 *                                      (A_proposal_replaced counts them)
 *   The applied input becomes u_{k-1} of the next step; A_reset restores clip(u_init).
 */
#ifndef BAL_STEP
#error "bal/grid.h: define BAL_STEP (the step's symbol prefix) first"
#endif

/* work vectors shared by A_h and A_h_next */
#define BAL_GRID_HSZ(k) BAL_MAX2(BAL_QX(h_SZ_##k), BAL_QX(h_next_SZ_##k))

typedef struct BAL_QX(work) {
  casadi_real cand[BAL_QX(M) * BAL_QX(NU)]; /* the candidates, rows in the order of C */
  casadi_real values[BAL_QX(M)];            /* h^(f(x, c)) of each candidate */
  casadi_real u_prev[BAL_QX(NU)];           /* u_{k-1} */
  casadi_real u_p[BAL_QX(NU)]; /* the proposal used (non-finite entries replaced by 0) */
  int order[BAL_QX(M)];
  int n_cand, n_replaced;
  const casadi_real* harg[BAL_GRID_HSZ(ARG)];
  casadi_real* hres[BAL_GRID_HSZ(RES)];
  casadi_int hiw[BAL_GRID_HSZ(IW) + 1];
  casadi_real hw[BAL_GRID_HSZ(W) + 1];
  int hmem, nmem, ready;
  long n_steps, n_decrease_infeasible;
} BAL_QX(work);

/* reset: u_{k-1} := clip(u_init) (A_U_INIT, NaN read as 0), counters to zero */
BAL_DECLARE_STEP_LIFECYCLE(BAL_QX)
int BAL_QX(step)(const casadi_real* x, const casadi_real* u_p, casadi_real* u_out,
                 casadi_real* h_out, int* status, BAL_QX(work)* wk);
/* candidates of the last step (0 after a refused state) */
int BAL_QX(n_candidates)(const BAL_QX(work)* wk);
/* which: 0 steps, 1 steps without a decreasing candidate */
long BAL_QX(counter)(const BAL_QX(work)* wk, int which);
/* u_{k-1} (A_NU values, owned by the work struct) */
const casadi_real* BAL_QX(u_prev)(const BAL_QX(work)* wk);
