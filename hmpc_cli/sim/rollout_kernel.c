/* Rollout kernel of the cross-entropy planner: hmpc_cli/sim/simulator.py's batched step in C.
 *
 * Appended by hmpc_cli/sim/rollout.py to the CasADi-generated functions of a system
 * and to its tables (HM_* macros, hm_rk4, hm_gaps, hm_phi, hm_region, hm_reset, ...).
 * hm_step_batch mirrors HybridSimulator.step / _first_crossing / _locate, hm_rollout
 * mirrors CrossEntropyPlanner.rollout_cost and hm_trajectory the simulation behind
 * CrossEntropyPlanner.trajectory, batch semantics included: the samples of one _locate
 * call iterate in lockstep until all have converged (as NumPy does), so every sample's
 * result is the NumPy one bit for bit, not only to the event time tolerance.
 */

#include <math.h>
#include <stdlib.h>
#include <string.h>

#define HM_ABI 4
#define HM_EXPORT __attribute__((visibility("default")))

typedef struct {
  const casadi_real *arg[HM_SZ_ARG + 4];
  casadi_real *res[HM_SZ_RES + 4];
  casadi_int iw[HM_SZ_IW + 1];
  casadi_real w[HM_SZ_W + 1];
  const double *u;   /* held input (HM_NU), not saturated: the generated RK4 clips it */
  double wd[HM_NW + 1];  /* disturbance: zero */
  int max_events;
  double tol;
} hm_ctx;

/* Event records of a one-sample trajectory (Event of sim.py, with its step index). */
typedef struct {
  int cap, n, step, overflow;
  int *step_of, *guard;
  double *tau, *before, *after;
} hm_rec;

/* Per-sample scratch of one batched step (capacity b samples). */
typedef struct {
  double *x_end, *x_hit, *x_lo, *g0, *g1, *rem, *tau, *lo, *hi, *t;
  int *cross, *n_events, *guard, *col, *todo, *rows;
  unsigned char *zeno;
  const double *u;  /* input of sample s: u + s * u_stride */
  size_t u_stride;
  hm_rec *rec;  /* events are recorded here if not NULL */
} hm_ws;

static void hm_rk4_call(hm_ctx *c, int m, const double *x, double h, double *out) {
  c->arg[0] = x; c->arg[1] = c->u; c->arg[2] = c->wd; c->arg[3] = &h;
  c->res[0] = out;
  hm_rk4[m](c->arg, c->res, c->iw, c->w, 0);
}

static void hm_gaps_call(hm_ctx *c, int m, const double *x, double *out) {
  c->arg[0] = x;
  c->res[0] = out;
  hm_gaps[m](c->arg, c->res, c->iw, c->w, 0);
}

static void hm_phi_call(hm_ctx *c, int m, const double *x, double t, double *phi,
                        double *dphi, double *xt) {
  c->arg[0] = x; c->arg[1] = c->u; c->arg[2] = c->wd; c->arg[3] = &t;
  c->res[0] = phi; c->res[1] = dphi; c->res[2] = xt;
  hm_phi[m](c->arg, c->res, c->iw, c->w, 0);
}

/* Whether x lies in guard g's activity region (every component >= 0; NaN is outside). */
static int hm_active(hm_ctx *c, int g, const double *x) {
  double r[HM_MAXR + 1];
  int j;
  if (hm_region[g] == 0) return 1;
  c->arg[0] = x;
  c->res[0] = r;
  hm_region[g](c->arg, c->res, c->iw, c->w, 0);
  for (j = 0; j < hm_nregion[g]; j++)
    if (!(r[j] >= 0.0)) return 0;
  return 1;
}

static void hm_reset_call(hm_ctx *c, int g, const double *x, double *out) {
  c->arg[0] = x;
  c->res[0] = out;
  hm_reset[g](c->arg, c->res, c->iw, c->w, 0);
}

static double hm_cost_call(hm_ctx *c, const double *x, const double *u) {
  double out;
  c->arg[0] = x; c->arg[1] = u;
  c->res[0] = &out;
  hm_cost(c->arg, c->res, c->iw, c->w, 0);
  return out;
}

/* Column of the smallest crossing phi: the first NaN if any (as np.argmin), else the first
 * minimum; non-crossing columns count as +inf. */
static int hm_argmin(const double *phis, const int *cross, int ng) {
  int j, best = 0;
  double v, vbest = INFINITY;
  for (j = 0; j < ng; j++) {
    v = cross[j] ? phis[j] : INFINITY;
    if (v != v) return j;
    if (v < vbest) { vbest = v; best = j; }
  }
  return best;
}

#define HM_U(ws, s) ((ws)->u + (size_t)(s) * (ws)->u_stride)

/* HybridSimulator._locate for the samples rows[0..n) of mode m, all in lockstep: the
 * bracket's before side lo[s], col[s], x_lo[s]. */
static void hm_locate(hm_ctx *c, hm_ws *ws, int m, const double *x, const int *rows, int n) {
  const int ng = hm_ng[m];
  const double tol = c->tol;
  double phis[HM_MAXG + 1], dphis[HM_MAXG + 1], xt[HM_NX], h, tj, tmin, phi, dphi, t_new;
  int i, j, s, it, one = 1, cnt, cc, past, nan_seen, done;
  int *cross;
  for (i = 0; i < n; i++) {
    s = rows[i];
    cross = ws->cross + s * HM_MAXG;
    h = ws->rem[s];
    ws->lo[s] = 0.0;
    ws->hi[s] = h;
    memcpy(ws->x_lo + s * HM_NX, x + s * HM_NX, sizeof(double) * HM_NX);
    ws->col[s] = -1;
    tmin = INFINITY;
    cnt = nan_seen = 0;
    for (j = 0; j < ng; j++) {
      if (!cross[j]) continue;
      if (ws->col[s] < 0) ws->col[s] = j;
      cnt++;
      tj = h * ws->g0[s * HM_MAXG + j] / (ws->g0[s * HM_MAXG + j] - ws->g1[s * HM_MAXG + j]);
      if (tj != tj) nan_seen = 1;
      else if (tj < tmin) tmin = tj;
    }
    if (nan_seen) tmin = NAN;  /* np.min propagates NaN */
    ws->t[s] = (isfinite(tmin) && tmin > 0.0 && tmin < h) ? tmin : 0.5 * h;
    one &= cnt == 1;
  }
  for (it = 0; it < 60; it++) {
    done = 1;
    for (i = 0; i < n; i++) {
      s = rows[i];
      c->u = HM_U(ws, s);
      hm_phi_call(c, m, x + s * HM_NX, ws->t[s], phis, dphis, xt);
      cc = one ? ws->col[s] : hm_argmin(phis, ws->cross + s * HM_MAXG, ng);
      phi = phis[cc];
      past = phi <= 0.0;
      if (past) {
        if (ws->t[s] < ws->hi[s]) ws->hi[s] = ws->t[s];
        ws->col[s] = cc;
      } else {
        if (ws->t[s] > ws->lo[s]) ws->lo[s] = ws->t[s];
        memcpy(ws->x_lo + s * HM_NX, xt, sizeof(double) * HM_NX);
      }
      done &= ws->hi[s] - ws->lo[s] <= tol;
      /* Newton step, kept for the update below (NaN when dphi = 0) */
      dphi = dphis[cc];
      t_new = ws->t[s] - (dphi != 0.0 ? phi / dphi : NAN);
      t_new += past ? -0.4 * tol : 0.4 * tol;
      ws->t[s] = (t_new > ws->lo[s] && t_new < ws->hi[s]) ? t_new : 0.5 * (ws->lo[s] + ws->hi[s]);
    }
    if (done) break;
  }
}

/* HybridSimulator._first_crossing for the samples todo[0..n): guard[s] (-1: none), tau[s],
 * x_hit[s] (x_end[s] if none). */
static void hm_first_crossing(hm_ctx *c, hm_ws *ws, const double *x, const int *mode,
                              const int *todo, int n) {
  int i, j, s, m, ng, nc, nr, any, g, *cross;
  for (i = 0; i < n; i++) {
    s = todo[i];
    ws->guard[s] = -1;
    ws->tau[s] = ws->rem[s];
    memcpy(ws->x_hit + s * HM_NX, ws->x_end + s * HM_NX, sizeof(double) * HM_NX);
  }
  for (m = 0; m < HM_NMODES; m++) {
    ng = hm_ng[m];
    if (ng == 0) continue;
    nc = 0;
    for (i = 0; i < n; i++) {
      s = todo[i];
      if (mode[s] != m) continue;
      hm_gaps_call(c, m, x + s * HM_NX, ws->g0 + s * HM_MAXG);
      hm_gaps_call(c, m, ws->x_end + s * HM_NX, ws->g1 + s * HM_MAXG);
      for (j = 0; j < ng; j++)
        ws->cross[s * HM_MAXG + j] = ws->g0[s * HM_MAXG + j] > 0.0
                                     && ws->g1[s * HM_MAXG + j] <= 0.0;
      ws->rows[nc++] = s;  /* candidates of mode m */
    }
    for (;;) {  /* rounds: a crossing outside its region is dropped and searched again */
      nr = 0;
      for (i = 0; i < nc; i++) {
        s = ws->rows[i];
        any = 0;
        for (j = 0; j < ng; j++) any |= ws->cross[s * HM_MAXG + j];
        if (any) ws->rows[nr++] = s;  /* rows with no crossing never get one back */
      }
      nc = nr;
      if (nr == 0) break;
      hm_locate(c, ws, m, x, ws->rows, nr);
      for (i = 0; i < nr; i++) {
        s = ws->rows[i];
        cross = ws->cross + s * HM_MAXG;
        g = hm_guard[m][ws->col[s]];
        if (hm_active(c, g, ws->x_lo + s * HM_NX)) {
          ws->tau[s] = ws->lo[s];
          ws->guard[s] = g;
          memcpy(ws->x_hit + s * HM_NX, ws->x_lo + s * HM_NX, sizeof(double) * HM_NX);
          for (j = 0; j < ng; j++) cross[j] = 0;
        } else {
          cross[ws->col[s]] = 0;
        }
      }
    }
  }
}

/* Appends sample s's event (time from the step start as sim.py: dt - rem + tau). */
static void hm_record(hm_rec *r, const hm_ws *ws, int s, int g, double dt, const double *after) {
  if (r->n >= r->cap) {
    r->overflow = 1;
    return;
  }
  r->step_of[r->n] = r->step;
  r->guard[r->n] = g;
  r->tau[r->n] = dt - ws->rem[s] + ws->tau[s];
  memcpy(r->before + (size_t)r->n * HM_NX, ws->x_hit + s * HM_NX, sizeof(double) * HM_NX);
  memcpy(r->after + (size_t)r->n * HM_NX, after, sizeof(double) * HM_NX);
  r->n++;
}

/* HybridSimulator.step (raise_zeno=False) of the samples run[0..n): advances x, mode by dt;
 * ws->zeno[s] = 1 if more than max_events events occurred (frozen after the last reset). */
static void hm_step_batch(hm_ctx *c, hm_ws *ws, double *x, int *mode, const int *run, int n,
                          double dt) {
  int i, s, g, nt = n;
  for (i = 0; i < n; i++) {
    s = run[i];
    ws->todo[i] = s;
    ws->rem[s] = dt;
    ws->n_events[s] = 0;
    ws->zeno[s] = 0;
  }
  while (nt > 0) {
    for (i = 0; i < nt; i++) {
      s = ws->todo[i];
      c->u = HM_U(ws, s);
      hm_rk4_call(c, mode[s], x + s * HM_NX, ws->rem[s], ws->x_end + s * HM_NX);
    }
    hm_first_crossing(c, ws, x, mode, ws->todo, nt);
    n = nt;
    nt = 0;
    for (i = 0; i < n; i++) {
      s = ws->todo[i];
      g = ws->guard[s];
      if (g < 0) {
        memcpy(x + s * HM_NX, ws->x_end + s * HM_NX, sizeof(double) * HM_NX);
        ws->rem[s] = 0.0;
        continue;
      }
      hm_reset_call(c, g, ws->x_hit + s * HM_NX, x + s * HM_NX);
      mode[s] = hm_target[g];
      if (ws->rec) hm_record(ws->rec, ws, s, g, dt, x + s * HM_NX);
      ws->rem[s] -= ws->tau[s];
      if (++ws->n_events[s] > c->max_events) {
        ws->zeno[s] = 1;
        ws->rem[s] = 0.0;
      }
      if (ws->rem[s] > 0.0 && !ws->zeno[s]) ws->todo[nt++] = s;
    }
  }
}

static void hm_init(hm_ctx *c, int max_events, double tol) {
  memset(c, 0, sizeof(*c));
  c->max_events = max_events;
  c->tol = tol;
}

/* Allocates the scratch of b samples in one block; returns the block (NULL: no memory). */
static void *hm_ws_alloc(hm_ws *ws, int b) {
  const size_t nb = b > 0 ? (size_t)b : 1, nd = nb * (3 * HM_NX + 2 * HM_MAXG + 5);
  const size_t ni = nb * (HM_MAXG + 5);
  double *d;
  int *k;
  void *block = calloc(nd * sizeof(double) + ni * sizeof(int) + nb, 1);
  if (block == 0) return 0;
  d = (double *)block;
  ws->x_end = d; d += nb * HM_NX;
  ws->x_hit = d; d += nb * HM_NX;
  ws->x_lo = d; d += nb * HM_NX;
  ws->g0 = d; d += nb * HM_MAXG;
  ws->g1 = d; d += nb * HM_MAXG;
  ws->rem = d; d += nb;
  ws->tau = d; d += nb;
  ws->lo = d; d += nb;
  ws->hi = d; d += nb;
  ws->t = d; d += nb;
  k = (int *)d;
  ws->cross = k; k += nb * HM_MAXG;
  ws->n_events = k; k += nb;
  ws->guard = k; k += nb;
  ws->col = k; k += nb;
  ws->todo = k; k += nb;
  ws->rows = k; k += nb;
  ws->zeno = (unsigned char *)k;
  ws->rec = 0;
  return block;
}

HM_EXPORT int hm_abi(void) { return HM_ABI; }

/* HybridSimulator.step of b samples: x (b, HM_NX), mode (b,), u (b, HM_NU), zero
 * disturbance; writes x_out, mode_out, zeno_out. Returns 0, -1 bad mode, -2 no memory. */
HM_EXPORT int hm_step(int b, const double *x, const int *mode, const double *u, double dt,
                      int max_events, double time_tol, double *x_out, int *mode_out,
                      unsigned char *zeno_out) {
  hm_ctx c;
  hm_ws ws;
  void *block;
  int i, *run;
  for (i = 0; i < b; i++)
    if (mode[i] < 0 || mode[i] >= HM_NMODES) return -1;
  block = hm_ws_alloc(&ws, b);
  run = (int *)malloc(sizeof(int) * (b > 0 ? b : 1));
  if (block == 0 || run == 0) { free(block); free(run); return -2; }
  hm_init(&c, max_events, time_tol);
  ws.u = u;
  ws.u_stride = HM_NU;
  memcpy(x_out, x, sizeof(double) * HM_NX * b);
  memcpy(mode_out, mode, sizeof(int) * b);
  for (i = 0; i < b; i++) run[i] = i;
  hm_step_batch(&c, &ws, x_out, mode_out, run, b, dt);
  for (i = 0; i < b; i++) zeno_out[i] = ws.zeno[i];
  free(block);
  free(run);
  return 0;
}

/* CrossEntropyPlanner.rollout_cost: u is (b, n_steps, HM_NU) C-contiguous; writes cost (b,)
 * and reached (b,). Returns 0, -1 bad mode, -2 no memory. */
HM_EXPORT int hm_rollout(int b, int n_steps, const double *x0, int mode0, const double *u,
                         double dt, double bound, int final_mode, int max_events,
                         double time_tol, double penalty, int absorbing, double *cost,
                         unsigned char *reached) {
  hm_ctx c;
  hm_ws ws;
  void *block;
  double *x, us[HM_NU + 1], zero[HM_NU + 1];
  int i, j, k, n, s, finite, *mode, *run;
  unsigned char *alive;
  if (mode0 < 0 || mode0 >= HM_NMODES) return -1;
  block = hm_ws_alloc(&ws, b);
  x = (double *)malloc(sizeof(double) * HM_NX * (b > 0 ? b : 1));
  mode = (int *)malloc(sizeof(int) * 2 * (b > 0 ? b : 1));
  alive = (unsigned char *)malloc(b > 0 ? b : 1);
  if (block == 0 || x == 0 || mode == 0 || alive == 0) {
    free(block); free(x); free(mode); free(alive);
    return -2;
  }
  run = mode + (b > 0 ? b : 1);
  hm_init(&c, max_events, time_tol);
  ws.u_stride = (size_t)n_steps * HM_NU;
  memset(zero, 0, sizeof(zero));
  for (i = 0; i < b; i++) {
    memcpy(x + i * HM_NX, x0, sizeof(double) * HM_NX);
    mode[i] = mode0;
    cost[i] = 0.0;
    alive[i] = 1;
    reached[i] = mode0 == final_mode;
  }
  for (k = 0; k < n_steps; k++) {
    n = 0;
    for (i = 0; i < b; i++)
      if (alive[i] && !(absorbing && reached[i])) run[n++] = i;
    if (n == 0) break;
    ws.u = u + (size_t)k * HM_NU;
    for (i = 0; i < n; i++) {
      s = run[i];
      for (j = 0; j < HM_NU; j++) {  /* np.clip to the mode's box */
        us[j] = HM_U(&ws, s)[j];
        if (us[j] < hm_ulo[mode[s]][j]) us[j] = hm_ulo[mode[s]][j];
        if (us[j] > hm_uhi[mode[s]][j]) us[j] = hm_uhi[mode[s]][j];
      }
      cost[s] += dt * hm_cost_call(&c, x + s * HM_NX, us);
    }
    hm_step_batch(&c, &ws, x, mode, run, n, dt);
    for (i = 0; i < n; i++) {
      s = run[i];
      finite = 1;
      for (j = 0; j < HM_NX; j++) finite &= isfinite(x[s * HM_NX + j]) != 0;
      alive[s] = !ws.zeno[s] && finite && cost[s] <= bound;
      if (!absorbing) {  /* reference cost: the rollout goes on; reached = ever entered */
        reached[s] = (reached[s] || mode[s] == final_mode) && alive[s];
        continue;
      }
      reached[s] = mode[s] == final_mode && alive[s];
      if (reached[s])
        cost[s] += (double)(n_steps - k - 1) * dt * hm_cost_call(&c, x + s * HM_NX, zero);
    }
  }
  for (i = 0; i < b; i++) cost[i] = (alive[i] ? cost[i] : INFINITY) + (reached[i] ? 0.0 : penalty);
  free(block); free(x); free(mode); free(alive);
  return 0;
}

/* CrossEntropyPlanner.trajectory's simulation of one sample: steps of u (n_steps, HM_NU)
 * until Zeno, a non-finite state or the final mode; writes the state and mode after each
 * step, the number of steps, and the events (step, time in the step, guard, states before
 * and after the reset; capacity cap). Returns 0, -1 bad mode, -2 no memory, -3 overflow. */
HM_EXPORT int hm_trajectory(int n_steps, const double *x0, int mode0, const double *u,
                            double dt, int final_mode, int max_events, double time_tol,
                            int cap, double *x_out, int *mode_out, int *n_done, int *ev_step,
                            double *ev_tau, int *ev_guard, double *ev_before,
                            double *ev_after, int *n_events) {
  hm_ctx c;
  hm_ws ws;
  hm_rec rec;
  void *block;
  double x[HM_NX];
  int k, j, mode = mode0, run = 0, finite;
  if (mode0 < 0 || mode0 >= HM_NMODES) return -1;
  block = hm_ws_alloc(&ws, 1);
  if (block == 0) return -2;
  hm_init(&c, max_events, time_tol);
  memset(&rec, 0, sizeof(rec));
  rec.cap = cap;
  rec.step_of = ev_step;
  rec.guard = ev_guard;
  rec.tau = ev_tau;
  rec.before = ev_before;
  rec.after = ev_after;
  ws.rec = &rec;
  ws.u_stride = 0;
  memcpy(x, x0, sizeof(double) * HM_NX);
  *n_done = 0;
  for (k = 0; k < n_steps; k++) {
    ws.u = u + (size_t)k * HM_NU;
    rec.step = k;
    hm_step_batch(&c, &ws, x, &mode, &run, 1, dt);
    memcpy(x_out + (size_t)k * HM_NX, x, sizeof(double) * HM_NX);
    mode_out[k] = mode;
    *n_done = k + 1;
    finite = 1;
    for (j = 0; j < HM_NX; j++) finite &= isfinite(x[j]) != 0;
    if (ws.zeno[0] || !finite || mode == final_mode) break;
  }
  *n_events = rec.n;
  free(block);
  return rec.overflow ? -3 : 0;
}
