"""Fixed-mode MPC (the paper's problems (12) and (14)) as one parametric NLP.

Multiple shooting on a chain of ``L = N + S`` links (see :mod:`hmpc_cli.mpc.layout`).
Link k maps node z_k to z_{k+1}:

    z_{k+1} = sum_m a_km Phi_m(z_k, u_k) + sum_g b_kg R_g(z_k) + e_k z_k

with Phi_m one RK4 (or Euler) interval of mode m, R_g the reset map of guard g and the
one-hot link type (a, b, e) a *parameter*. With ``input_hold = "foh"`` the input of a flow
interval goes linearly from u_k to u_{k+1} (the low level's first-order-hold feed-forward,
so an undisturbed plant follows the plan); the last interval before a guard node ends at
the virtual input, the horizon's last interval holds its input.

Path rows of node k, with bounds chosen per solve (an inactive row gets infinite bounds):

* one row per guard g: s_kg q_g(z_k) - kappa_kg + sigma_k. Guard-avoid (>= 0, s = +1,
  kappa from the tube margin), guard-hit at the switching node (>= 0 here and
  q_G(z_k) - sigma_k <= 0 in the next row: |q_G| <= sigma_k), or off;
* the virtual pass-through row: -q_G(Phi(z_k, u_k)) - kappa + sigma_k >= 0 at each guard
  node, i.e. one more interval of the source flow with the virtual input u_k puts the
  whole tube past the guard (problem (14));
* the guard's activity-region rows at the switching node (+ sigma_k >= 0);
* terminal-set rows at the last node (+ sigma_L >= 0).

sigma_k >= 0 is one slack per node with an exact L1 penalty ``soft_penalty * sum sigma_k``
in the cost: whenever the hybrid constraints can be met, the solution meets them exactly
(sigma = 0); when a disturbance has made them infeasible (the planned guard time can no
longer be reached, say) the solve returns the least-relaxed plan instead of failing, and
the relaxation max sigma_k is reported with every solve. ``soft_penalty = 0`` fixes
sigma = 0: the hard constraints of the paper.

Inputs are bounded by the (tightened) box of each link's mode through the variable
bounds; reset-link inputs are the virtual inputs. Built once per (system, horizon,
S_max) and re-solved with parameters, bounds and a primal-dual warm start.
"""

from __future__ import annotations

from typing import Literal

import casadi as ca
import numpy as np
from pydantic import BaseModel, ConfigDict, Field, model_validator

from hmpc_cli.hybrid import HybridSystem
from hmpc_cli.messages import Trajectory
from hmpc_cli.mpc.layout import FLOW, HOLD, RESET, ChainLayout, NodeSchedule

INF = np.inf
VIRTUAL_INPUT_WEIGHT = 1e-3


class MPCSettings(BaseModel):
    """Fixed-mode MPC settings."""

    model_config = ConfigDict(extra="forbid")
    kind: Literal["fixed_mode"] = Field("fixed_mode", description="mode-schedule MPC on "
                                        "the chain transcription (any system)")
    rate_hz: int = Field(10, gt=0, description="MPC re-solve rate [Hz]")
    nodes_per_second: int = Field(60, gt=0, description="NLP node rate: node step = 1/this")
    horizon: float = Field(3.0, gt=0.0, description="receding horizon [s]")
    max_switches: int = Field(10, ge=0, description="guard events the NLP chain can hold")
    integrator: Literal["rk4", "euler"] = "rk4"
    input_hold: Literal["foh", "zoh"] = Field(
        "foh", description="input between nodes: first-order hold (linear from u_k to "
                           "u_k+1, as the low level feeds it forward) or zero-order hold")
    robust: bool = Field(True, description="virtual pass-through node (problem (14))")
    soft_penalty: float = Field(
        1e4, ge=0.0, description="L1 penalty on relaxing guard, virtual-node, region and "
                                 "terminal rows (0: hard constraints, as in the paper)")
    tube_margin: float = Field(0.025, ge=0.0, description="tube radius diam T(dt) [state norm]")
    input_margin: float = Field(0.0, ge=0.0, description="input-box tightening per side")
    solver: Literal["ipopt", "fatrop", "sqpmethod"] = "ipopt"
    solver_options: dict = Field(default_factory=dict, description="passed to the plugin")
    max_iter: int = Field(200, gt=0)
    warm_start: bool = True
    resolve_on_impact: bool = True
    final_domain_nlp: bool = Field(
        True, description="solve schedules with no switch left on the final domain's own, "
                          "smaller NLP (same problem, no switching rows)")

    @model_validator(mode="after")
    def _stagewise_for_fatrop(self) -> MPCSettings:
        if self.solver == "fatrop" and self.input_hold == "foh":
            raise ValueError('solver "fatrop" needs stage-wise dynamics: set input_hold = '
                             '"zoh" (a first-order hold couples each interval to the next '
                             'input)')
        return self

    def period_steps(self) -> list[tuple[str, int]]:
        """Step rates the MPC period must be a whole number of (key path, rate [Hz])."""
        return [("mpc.nodes_per_second", self.nodes_per_second)]

    def scenario_problems(self) -> list[str]:
        """``mpc.key: reason`` lines for settings that do not fit together."""
        n = self.horizon * self.nodes_per_second
        if n < 2 or abs(n - round(n)) > 1e-9 * max(1.0, n):
            return ["mpc.horizon: must be a whole number (>= 2) of node steps"]
        return []

    @property
    def dt(self) -> float:
        """Node step [s]."""
        return 1.0 / self.nodes_per_second

    @property
    def n_intervals(self) -> int:
        return int(round(self.horizon * self.nodes_per_second))

    @property
    def nodes_per_period(self) -> int:
        return self.nodes_per_second // self.rate_hz


class FixedModeNLP:
    """The parametric fixed-mode NLP on a chain of N + S links (built once).

    Args:
        system: the hybrid system (the controllers' model).
        settings: MPC settings.
        switches: S, the guard events the chain holds (default ``settings.max_switches``).
            With S = 0 the NLP is the final domain's plain MPC: only that mode's flow and
            guard-avoid rows, no reset, virtual-node or region rows (a much smaller KKT
            system for the solves after the last scheduled switch).
    """

    def __init__(self, system: HybridSystem, settings: MPCSettings,
                 switches: int | None = None) -> None:
        self.system = system
        self.s = settings
        self.S = settings.max_switches if switches is None else switches
        self.N = settings.n_intervals
        self.L = self.N + self.S
        self.dt = settings.dt
        self.n, self.m = system.n_x, system.n_u
        self.G = len(system.guards)
        final = system.mode_index(system.final_mode)
        # modes with a flow in the chain, guards with rows (local column order)
        self.modes_in = list(range(len(system.modes))) if self.S else [final]
        self.row_guards = list(range(self.G)) if self.S else system.guards_of(final)
        self._mcol = {mode: c for c, mode in enumerate(self.modes_in)}
        self._gcol = {g: c for c, g in enumerate(self.row_guards)}
        self.M, self.Gr = len(self.modes_in), len(self.row_guards)
        self.R = max([g.region.size1_out(0) for g in system.guards if g.region is not None]
                     or [0]) if self.S else 0
        self.T = system.terminal_set.size1_out(0) if system.terminal_set is not None else 0
        # rows per node: guard rows, then (if S > 0) guard-hit upper side, virtual, region
        self.P = self.Gr + (2 + self.R if self.S else 0)
        self._guards_of = [system.guards_of(i) for i in range(len(system.modes))]
        # guard-avoid offsets: margin 0 for the guard just crossed, else the tube margin
        self._kappa = [(g.kappa(0.0, past=False), g.kappa(settings.tube_margin, past=False))
                       for g in system.guards]
        self._build()

    # ------------------------------------------------------------------ build
    def _interval(self, mode: int, z, u, u_end):
        """One interval of ``mode`` from z with the input going linearly from u to u_end."""
        f = self.system.modes[mode].flow
        w = ca.DM.zeros(self.system.n_w)
        h = self.dt
        if self.s.integrator == "euler":
            return z + h * f(z, u, w)
        u_mid = 0.5 * (u + u_end)
        k1 = f(z, u, w)
        k2 = f(z + h / 2 * k1, u_mid, w)
        k3 = f(z + h / 2 * k2, u_mid, w)
        k4 = f(z + h * k3, u_end, w)
        return z + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)

    def _build(self) -> None:
        n, m, L, G, M, Gr = self.n, self.m, self.L, self.G, self.M, self.Gr
        sysm, switching = self.system, self.S > 0
        Z = [ca.SX.sym(f"z{k}", n) for k in range(L + 1)]
        U = [ca.SX.sym(f"u{k}", m) for k in range(L)]
        Sg = [ca.SX.sym(f"sigma{k}") for k in range(L + 1)]
        pa = ca.SX.sym("a", L, M)
        pb = ca.SX.sym("b", L, G if switching else 0)
        pe = ca.SX.sym("e", L)
        pw = ca.SX.sym("w", L)
        pv = ca.SX.sym("v", L)
        pf = ca.SX.sym("foh", L)  # 1: the interval's input ends at the next link's input
        ps = ca.SX.sym("s", L + 1, Gr)
        pk = ca.SX.sym("kappa", L + 1, Gr)
        nsw = L + 1 if switching else 0
        pbeta = ca.SX.sym("beta", nsw, G)
        pkv = ca.SX.sym("kappa_v", nsw)
        phit = ca.SX.sym("hit", nsw, G)
        zs = ca.SX.sym("zs", n)

        src = [self._mcol.get(sysm.mode_index(g.source), 0) for g in sysm.guards]
        q = [ca.Function(f"q_{g.name}", [zs], [g.q_expr(zs)]) for g in sysm.guards]
        regions = []
        for g in sysm.guards if switching else ():
            r = g.region(zs) if g.region is not None else ca.SX.zeros(0)
            pad = ca.vertcat(r, ca.SX.zeros(self.R - r.size1()))
            regions.append(ca.Function(f"r_{g.name}", [zs], [pad]))
        stage = sysm.stage_cost
        J = 0
        g_rows = []

        def path(k, z, flows, sk):
            qz = {i: q[i](z) for i in (range(G) if switching else self.row_guards)}
            rows = [ps[k, c] * qz[i] - pk[k, c] + sk for c, i in enumerate(self.row_guards)]
            if not switching:
                return rows
            rows.append(sum(phit[k, i] * qz[i] for i in range(G)) - sk)
            virt = 0
            for i in range(G):
                virt += pbeta[k, i] * (-q[i](flows[src[i]]))
            rows.append(virt - pkv[k] + sk)
            reg = ca.SX.zeros(self.R)
            for i in range(G):
                reg += pbeta[k, i] * regions[i](z)
            rows.extend(ca.vertsplit(reg + sk) if self.R else [])
            return rows

        for k in range(L):
            foh = self.s.input_hold == "foh" and k + 1 < L  # structural: zoh keeps stages
            u_end = U[k] + pf[k] * (U[k + 1] - U[k]) if foh else U[k]
            flows = [self._interval(i, Z[k], U[k], u_end) for i in self.modes_in]
            nxt = pe[k] * Z[k]
            for c in range(M):
                nxt += pa[k, c] * flows[c]
            for i, g in enumerate(sysm.guards if switching else ()):
                nxt += pb[k, i] * g.reset(Z[k])
            g_rows.append(Z[k + 1] - nxt)
            g_rows.extend(path(k, Z[k], flows, Sg[k]))
            J += pw[k] * stage(Z[k], U[k]) + pv[k] * ca.sumsqr(U[k])
        last_flows = [self._interval(i, Z[L], ca.DM.zeros(m), ca.DM.zeros(m))
                      for i in self.modes_in] if switching else []
        g_rows.extend(path(L, Z[L], last_flows, Sg[L]))
        if self.T:
            g_rows.append(sysm.terminal_set(Z[L]) + Sg[L])
        J += self.s.soft_penalty * ca.sum1(ca.vertcat(*Sg))
        w_vars = []
        for k in range(L):
            w_vars += [Z[k], U[k], Sg[k]]
        w_vars += [Z[L], Sg[L]]
        p = ca.vertcat(ca.vec(pa), ca.vec(pb), pe, pw, pv, pf, ca.vec(ps), ca.vec(pk),
                       ca.vec(pbeta), pkv, ca.vec(phit))
        g_rows_flat = ca.vertcat(*g_rows)
        nlp = {"x": ca.vertcat(*w_vars), "p": p, "f": J, "g": g_rows_flat}
        opts = {"expand": True}
        plugin_opts = dict(self.s.solver_options)
        plugin_opts.pop("ipopt_warm", None)
        if self.s.solver == "ipopt":
            ipopt = {"print_level": 0, "sb": "yes", "max_iter": self.s.max_iter,
                     "tol": 1e-8, "constr_viol_tol": 1e-8, "mu_strategy": "adaptive"}
            ipopt.update(plugin_opts.pop("ipopt", {}))
            opts.update({"ipopt": ipopt, "print_time": False})
        elif self.s.solver == "sqpmethod":
            opts.update({"max_iter": self.s.max_iter, "print_time": False,
                         "print_header": False, "print_iteration": False,
                         "qpsol": "qrqp",
                         "qpsol_options": {"print_iter": False, "print_header": False,
                                           "error_on_fail": False}})
        else:
            rows = n + self.P
            equality = [(r % rows) < n and r < L * rows for r in range(g_rows_flat.size1())]
            opts.update({"structure_detection": "auto", "print_time": False,
                         "equality": equality,
                         "fatrop": {"print_level": 0, "max_iter": self.s.max_iter}})
        opts.update(plugin_opts)
        self.solver = ca.nlpsol("fixed_mode_mpc", self.s.solver, nlp, opts)
        self._warm_solver = self.solver
        if self.s.solver == "ipopt":
            warm = dict(opts)
            warm["ipopt"] = {**opts["ipopt"], "warm_start_init_point": "yes",
                             "mu_init": 1e-6, "warm_start_bound_push": 1e-9,
                             "warm_start_mult_bound_push": 1e-9,
                             "warm_start_slack_bound_push": 1e-9}
            warm["ipopt"].update(self.s.solver_options.get("ipopt_warm", {}))
            warm.pop("ipopt_warm", None)
            self._warm_solver = ca.nlpsol("fixed_mode_mpc_warm", "ipopt", nlp, warm)
        self.nx_var = nlp["x"].size1()
        self.ng = nlp["g"].size1()
        self.np = p.size1()
        self._g_fun = ca.Function("g", [nlp["x"], p], [nlp["g"]])
        self.rows_per_link = n + self.P
        stride = n + m + 1
        self.z_idx = np.array([[k * stride + i for i in range(n)] for k in range(L + 1)])
        self.u_idx = np.array([[k * stride + n + i for i in range(m)] for k in range(L)])
        self.s_idx = np.array([k * stride + n + m for k in range(L)] + [L * stride + n])

    # ------------------------------------------------------------ problem data
    def _path_row(self, k: int) -> int:
        """First path row of node k."""
        return k * self.rows_per_link + (self.n if k < self.L else 0)

    def problem_data(self, ns: NodeSchedule, lay: ChainLayout, x0: np.ndarray):
        """Parameters and bounds of one solve: (p, lbx, ubx, lbg, ubg)."""
        n, L, G, Gr = self.n, self.L, self.G, self.Gr
        sysm, d = self.system, self.s.tube_margin
        nsw = L + 1 if self.S else 0
        a = np.zeros((L, self.M))
        b = np.zeros((L, G if self.S else 0))
        e = np.zeros(L)
        wk = np.zeros(L)
        vk = np.zeros(L)
        foh = np.zeros(L)
        sg = np.zeros((L + 1, Gr))
        kap = np.zeros((L + 1, Gr))
        beta = np.zeros((nsw, G))
        kv = np.zeros(nsw)
        hit = np.zeros((nsw, G))
        lbx = np.full(self.nx_var, -INF)
        ubx = np.full(self.nx_var, INF)
        lbx[self.s_idx] = 0.0
        ubx[self.s_idx] = INF if self.s.soft_penalty > 0.0 else 0.0
        lbg = np.full(self.ng, -INF)
        ubg = np.full(self.ng, INF)
        lbx[self.z_idx[0]] = ubx[self.z_idx[0]] = x0
        for k in range(L):
            lbg[k * self.rows_per_link: k * self.rows_per_link + n] = 0.0
            ubg[k * self.rows_per_link: k * self.rows_per_link + n] = 0.0
            typ, mode = lay.link_type[k], lay.link_mode[k]
            lo = hi = np.zeros(self.m)
            if typ == FLOW:
                a[k, self._mcol[mode]], wk[k] = 1.0, self.dt
                lo, hi = self._input_box(mode)
                # first-order hold up to the next link's input (the virtual input before
                # a guard node); the horizon's last interval holds its input
                if self.s.input_hold == "foh" and k + 1 < L and lay.link_type[k + 1] != HOLD:
                    foh[k] = 1.0
            elif typ == RESET:
                b[k, lay.link_guard[k]] = 1.0
                if self.s.robust:
                    vk[k] = VIRTUAL_INPUT_WEIGHT * self.dt
                    lo, hi = self._input_box(mode)
            else:
                e[k] = 1.0
            lbx[self.u_idx[k]], ubx[self.u_idx[k]] = lo, hi
        for k in range(1, lay.last + 1):
            j = int(lay.seg[k])
            mode = ns.modes[j]
            row = self._path_row(k)
            entered_by = ns.guards[j - 1] if j > 0 else -1
            is_guard_node = j < len(ns.guards) and lay.local[k] == ns.counts[j]
            if lay.first_after_reset[k]:
                continue
            for gi in self._guards_of[mode]:
                c = self._gcol[gi]
                if is_guard_node and gi == ns.guards[j]:  # guard-hit: |q| <= sigma
                    sg[k, c], kap[k, c], hit[k, gi] = 1.0, 0.0, 1.0
                    lbg[row + c] = ubg[row + Gr] = 0.0
                    continue
                sg[k, c] = 1.0
                kap[k, c] = self._kappa[gi][0 if gi == entered_by else 1]
                lbg[row + c] = 0.0
            if is_guard_node:
                gi = ns.guards[j]
                g = sysm.guards[gi]
                if self.s.robust:
                    beta[k, gi], kv[k] = 1.0, g.kappa(d, past=True)
                    lbg[row + Gr + 1] = 0.0
                else:
                    beta[k, gi] = 1.0  # region rows only
                dims = g.region.size1_out(0) if g.region is not None else 0
                lbg[row + Gr + 2: row + Gr + 2 + dims] = 0.0
        if self.T:
            lbg[self.ng - self.T:] = 0.0
        p = np.concatenate([a.ravel(order="F"), b.ravel(order="F"), e, wk, vk, foh,
                            sg.ravel(order="F"), kap.ravel(order="F"),
                            beta.ravel(order="F"), kv, hit.ravel(order="F")])
        return p, lbx, ubx, lbg, ubg

    def _input_box(self, mode: int) -> tuple[np.ndarray, np.ndarray]:
        """The mode's input box shrunk by ``input_margin`` per side (never past its centre)."""
        md = self.system.modes[mode]
        lo = np.array(md.u_lower) + self.s.input_margin
        hi = np.array(md.u_upper) - self.s.input_margin
        mid = 0.5 * (np.array(md.u_lower) + np.array(md.u_upper))
        return np.minimum(lo, mid), np.maximum(hi, mid)

    # ------------------------------------------------------------------ solve
    def solve(self, w0, p, lbx, ubx, lbg, ubg, lam_x0=None, lam_g0=None):
        """One solve. Returns (solution dict, status, iterations, success)."""
        args = {"x0": w0, "p": p, "lbx": lbx, "ubx": ubx, "lbg": lbg, "ubg": ubg}
        solver = self.solver
        if lam_x0 is not None and lam_g0 is not None:
            lam_g0 = np.where(np.isfinite(lbg) | np.isfinite(ubg), lam_g0, 0.0)
            args.update(lam_x0=lam_x0, lam_g0=lam_g0)
            solver = self._warm_solver
        sol = solver(**args)
        st = solver.stats()
        status = str(st.get("return_status", st.get("success")))
        iters = st.get("iter_count", st.get("iterations", {}).get("iter", [0])[-1]
                       if isinstance(st.get("iterations"), dict) else 0)
        return sol, status, int(iters), bool(st.get("success", False))

    def violation(self, w, p, lbx, ubx, lbg, ubg) -> float:
        """Largest constraint or bound violation at primal point w."""
        g = np.asarray(self._g_fun(w, p)).ravel()
        v = [np.max(np.maximum(lbg - g, 0.0), initial=0.0),
             np.max(np.maximum(g - ubg, 0.0), initial=0.0),
             np.max(np.maximum(lbx - w, 0.0), initial=0.0),
             np.max(np.maximum(w - ubx, 0.0), initial=0.0)]
        return float(max(v))

    def constraints(self, w, p) -> np.ndarray:
        """Constraint values g(w, p), shape (ng,)."""
        return np.asarray(self._g_fun(w, p)).ravel()

    # ------------------------------------------------------------- warm start
    def remap_vectors(self, node_map, w, lam_x, lam_g, source: FixedModeNLP | None = None):
        """Re-indexes primal/dual vectors of ``source`` (default: this NLP) node by node
        onto this NLP (see :func:`layout.remap`); duals only within one NLP (None else)."""
        src = source or self
        L = self.L
        link_map = np.minimum(node_map[:L], src.L - 1)
        new_w = np.zeros(self.nx_var) if src is not self else w.copy()
        new_w[self.z_idx] = w[src.z_idx[node_map]]
        new_w[self.u_idx] = w[src.u_idx[link_map]]
        new_w[self.s_idx] = w[src.s_idx[node_map]]
        if lam_x is None or lam_g is None or src is not self:
            return new_w, None, None
        new_lx = lam_x.copy()
        new_lx[self.z_idx] = lam_x[self.z_idx[node_map]]
        new_lx[self.u_idx] = lam_x[self.u_idx[link_map]]
        new_lx[self.s_idx] = lam_x[self.s_idx[node_map]]
        rows = np.arange(self.rows_per_link)
        new_lg = lam_g.copy()
        new_lg[(np.arange(L)[:, None] * self.rows_per_link + rows).ravel()] = \
            lam_g[(link_map[:, None] * self.rows_per_link + rows).ravel()]
        return new_w, new_lx, new_lg

    # ------------------------------------------------------------- trajectory
    def trajectory(self, w: np.ndarray, ns: NodeSchedule, lay: ChainLayout) -> Trajectory:
        """The planned hybrid trajectory (real nodes only; resets as node pairs)."""
        k_last = lay.last
        x = w[self.z_idx[: k_last + 1]]
        u = w[self.u_idx[: max(k_last, 1)]]
        u = np.vstack([u, u[-1:]])[: k_last + 1]
        steps = np.where(lay.link_type[:k_last] == FLOW, self.dt, 0.0)
        t = np.concatenate([[0.0], np.cumsum(steps)])
        seg = lay.seg[: k_last + 1].copy()
        mode = np.array([ns.modes[j] for j in seg])
        return Trajectory(t, x, u, mode, seg, tuple(ns.guards), self.s.input_hold)


class FixedModeNLPs:
    """The fixed-mode NLPs of one (system, settings), each built once: the switching chain
    (S = ``max_switches``) and, with ``final_domain_nlp``, the final domain's (S = 0)."""

    def __init__(self, system: HybridSystem, settings: MPCSettings) -> None:
        self.switching = FixedModeNLP(system, settings)
        self.final = FixedModeNLP(system, settings, switches=0) \
            if settings.final_domain_nlp else None
        self._final_mode = system.mode_index(system.final_mode)
        self.N, self.dt = self.switching.N, self.switching.dt

    def for_schedule(self, ns: NodeSchedule) -> FixedModeNLP:
        """The NLP that solves node schedule ``ns``."""
        if self.final is not None and ns.modes == (self._final_mode,):
            return self.final
        return self.switching
