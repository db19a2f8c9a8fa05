/* bal/problem.h: the work struct and entry points of one emitted problem P = BAL_PROBLEM
 * (e.g. the slack problem (2.24)). Included once per problem by the generated <name>.h,
 * after <name>_config.h, which documents P (parameters, variables, tolerances, retries)
 * and defines its sizes P_NP, P_NW, P_NG, P_N_SOLVERS, P_SZ_*, offsets P_P_<parameter>,
 * P_W_<variable>.
 *
 * Entry points: P_init, P_finalize, P_alloc, P_free, P_cold_start, P_warm_start,
 * P_warm_start_primal, P_solve, P_solve_from, P_solve_lead, P_attempts, P_inaccurate, P_primal,
 * P_value, P_residuals.
 * No include guard: included once per prefix.
 */
#ifndef BAL_PROBLEM
#error "bal/problem.h: define BAL_PROBLEM (the problem's symbol prefix) first"
#endif

typedef struct BAL_PX(work) {
  /* warm start, read by P_solve: set it with P_cold_start / P_warm_start or by hand */
  casadi_real x0[BAL_PX(NW)], lam_x0[BAL_PX(NW)], lam_g0[BAL_PX(NG) + 1];
  /* solution, written by P_solve */
  casadi_real x[BAL_PX(NW)], lam_x[BAL_PX(NW)], lam_g[BAL_PX(NG) + 1], g[BAL_PX(NG) + 1];
  casadi_real lam_p[BAL_PX(NP) + 1];
  casadi_real f, pr_inf, du_inf, feas;
  int attempts; /* solver runs in the last P_solve (> 1: retried) */
  int which;    /* the solver (attempt index) of the last attempt run */
  /* 1: the attempt from a second start (P_solve_from / P_solve_lead) starts with the warm
     multipliers lam_x0/lam_g0 instead of zero ones (0 after P_init) */
  int second_duals;
  /* 1 if the last P_solve returned BAL_OK from a solver that stopped at its acceptable
     level (IPOPT's Solved_To_Acceptable_Level): balustrade's backend reports that solve
     optimal_inaccurate (used, flagged, never certified optimal), else 0 */
  int inaccurate;
  /* the last BAL_FEASIBLE attempt of a P_solve, restored if no attempt converges */
  casadi_real kx[BAL_PX(NW)], klam_x[BAL_PX(NW)], klam_g[BAL_PX(NG) + 1], kg[BAL_PX(NG) + 1];
  casadi_real kf, kpr_inf, kdu_inf, kfeas;
  /* CasADi work vectors (sizes from <name>_casadi.h), shared by the solver and retries */
  const casadi_real* arg[BAL_PX(SZ_ARG)];
  casadi_real* res[BAL_PX(SZ_RES)];
  casadi_int iw[BAL_PX(SZ_IW) + 1];
  casadi_real w[BAL_PX(SZ_W) + 1];
  const casadi_real* karg[BAL_PX(kkt_SZ_ARG)];
  casadi_real* kres[BAL_PX(kkt_SZ_RES)];
  casadi_int kiw[BAL_PX(kkt_SZ_IW) + 1];
  casadi_real kw[BAL_PX(kkt_SZ_W) + 1];
  int mem[BAL_PX(N_SOLVERS)], kmem, ready;
} BAL_PX(work);

/* Take the CasADi memory (incref + checkout) and cold-start; 0 on success, -1 if no
   memory is left (compile with -DCASADI_MAX_NUM_THREADS=n for n concurrent users). */
int BAL_PX(init)(BAL_PX(work)* wk);
/* Give the memory back (release + decref). */
void BAL_PX(finalize)(BAL_PX(work)* wk);
/* calloc + P_init (NULL on failure) / P_finalize + free. */
BAL_PX(work)* BAL_PX(alloc)(void);
void BAL_PX(free)(BAL_PX(work)* wk);
/* Warm start := the declared initial values, zero multipliers. */
void BAL_PX(cold_start)(BAL_PX(work)* wk);
/* Warm start := the last solution (primal and multipliers). */
void BAL_PX(warm_start)(BAL_PX(work)* wk);
/* Warm start := the last solution's primal, zero multipliers (epigraph variables at their
   initial values): what balustrade's backend does with a solution that did not converge. */
void BAL_PX(warm_start_primal)(BAL_PX(work)* wk);
/* Solve with parameters p (P_NP values) from the warm start in wk; returns BAL_*
   (call P_warm_start afterwards to start the next solve from this solution).
   A NaN or inf parameter returns BAL_BAD_INPUT without solving (x and f are then NaN);
   a NaN or inf in the start (x0, lam_x0, lam_g0) makes it the cold start (P_cold_start).
   With an iteration budget (P_BUDGET > 0) a solve stopped by it returns BAL_TRUNCATED
   (its iterate in x; P_truncated_feasible tells whether it may be used). */
int BAL_PX(solve)(BAL_PX(work)* wk, const casadi_real* p);
/* P_solve, but if the first attempt fails, the first solver runs once more from the primal
   `second` (P_NW values, zero multipliers; NULL or a NaN/inf entry: none) before the
   cold-start retries. */
int BAL_PX(solve_from)(BAL_PX(work)* wk, const casadi_real* p, const casadi_real* second);
/* P_solve_from, but first (lead > 0) the cold-start retry `lead` runs, then the chain as
   usual without that retry (a recovery step, balustrade.backends.recovery); lead 0: none. */
int BAL_PX(solve_lead)(BAL_PX(work)* wk, const casadi_real* p, const casadi_real* second,
                       int lead);
/* 1 if status is BAL_TRUNCATED and the iterate in wk meets every row and bound within
   P_TRUNC_TOL (absolute: Solution.feasible_within of balustrade's backend), else 0. */
int BAL_PX(truncated_feasible)(const BAL_PX(work)* wk, int status);
/* The solver runs of the last P_solve (1: no retry; a retry that would repeat an attempt
   already run, the same solver from the same start, is skipped and not counted). */
int BAL_PX(attempts)(const BAL_PX(work)* wk);
/* 1 if the last P_solve's BAL_OK is a stop at the solver's acceptable level (the
   backend's optimal_inaccurate: converged only to the reduced tolerances), else 0. */
int BAL_PX(inaccurate)(const BAL_PX(work)* wk);
/* Pointers into wk, for foreign-function callers. */
const casadi_real* BAL_PX(primal)(const BAL_PX(work)* wk);
casadi_real BAL_PX(value)(const BAL_PX(work)* wk);
/* out[0] = primal violation, out[1] = dual residual, out[2] = scaled violation */
void BAL_PX(residuals)(const BAL_PX(work)* wk, casadi_real* out);
