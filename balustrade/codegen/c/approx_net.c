/* bal/approx_net.c: h^ of A = BAL_STEP evaluated as dense loops over the weights of its
 * network (A_NET = 1; emit_approximate(..., network)), instead of the CasADi-generated
 * scalar code of A_h / A_h_next. The CasADi code writes every weight into the instruction
 * stream (~100 kB for a 5 x 32 network): fetched from memory when the caches are cold,
 * which dominates a single evaluation (the certification of Algorithm 7.5). Here the code is
 * a few loops and the weights one array (A_NET_W, 8 bytes a weight).
 *
 * h^(x) = T(W_L s(... s(W_1 (x - mean) / scale + b_1) ...) + b_L), s = softplus with
 * the network's threshold A_NET_THRESHOLD (balustrade.learn.train.SOFTPLUS_THRESHOLD, torch's
 * 20; z above it: z, else log1p(exp(z))), T = the cube if A_NET_CUBE.
 * The operations are those of balustrade.learn.export.expression in the same order (each
 * row summed over its inputs in order, then the bias), so the values are the CasADi code's.
 * h^(f(x, u)) takes f from the CasADi-generated A_f (x, u) -> x+.
 * From <name>_config.h: A_NET_NL (layers), A_NET_SIZES (NL + 1 widths, input first),
 * A_NET_MAXW (largest width), A_NET_W (the W_k row-major, concatenated), A_NET_B,
 * A_NET_MEAN, A_NET_SCALE, A_NET_CUBE, A_NET_THRESHOLD. Included by bal/approx.c.
 */
#include <math.h>

static const int BAL_QX(net_sizes)[BAL_QX(NET_NL) + 1] = BAL_QX(NET_SIZES);
static const casadi_real BAL_QX(net_w)[] = BAL_QX(NET_W);
static const casadi_real BAL_QX(net_b)[] = BAL_QX(NET_B);
static const casadi_real BAL_QX(net_mean)[BAL_QX(NX)] = BAL_QX(NET_MEAN);
static const casadi_real BAL_QX(net_scale)[BAL_QX(NX)] = BAL_QX(NET_SCALE);

/* h^(x) of the network */
static casadi_real BAL_QX(net_eval)(const casadi_real* x) {
  casadi_real buf[2][BAL_QX(NET_MAXW)], s;
  const casadi_real *w = BAL_QX(net_w), *b = BAL_QX(net_b), *z;
  casadi_real* y;
  int k, i, j, m, n, cur = 0;
  for (i = 0; i < BAL_QX(NX); ++i) {
    buf[0][i] = (x[i] - BAL_QX(net_mean)[i]) / BAL_QX(net_scale)[i];
  }
  for (k = 0; k < BAL_QX(NET_NL); ++k) {
    n = BAL_QX(net_sizes)[k];
    m = BAL_QX(net_sizes)[k + 1];
    z = buf[cur];
    y = buf[1 - cur];
    for (i = 0; i < m; ++i) {
      s = 0.0;
      for (j = 0; j < n; ++j) s += w[j] * z[j];
      s += b[i];
      if (k < BAL_QX(NET_NL) - 1) s = s > BAL_QX(NET_THRESHOLD) ? s : log1p(exp(s));
      y[i] = s;
      w += n;
    }
    b += m;
    cur = 1 - cur;
  }
  s = buf[cur][0];
  return BAL_QX(NET_CUBE) ? s * (s * s) : s;
}

/* h^(f(x, u)); NAN if f fails */
static casadi_real BAL_QX(net_eval_next)(BAL_QX(work)* wk, const casadi_real* x,
                                         const casadi_real* u) {
  casadi_real xn[BAL_QX(NX)];
  wk->harg[0] = x;
  wk->harg[1] = u;
  wk->hres[0] = xn;
  if (BAL_QX(f)(wk->harg, wk->hres, wk->hiw, wk->hw, wk->fmem)) return NAN;
  return BAL_QX(net_eval)(xn);
}
