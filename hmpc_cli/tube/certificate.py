"""Prop. 3: an E-ISS Lyapunov certificate of the PD tracking-error dynamics.

The error e = x - x_ref of the low level u = u_ff + K (x_ref - x) obeys, linearised at a
nominal (x~, u~) of the initial mode (A = df/dx, B = df/du there),

    e' = A_cl e + w_e,   A_cl = A - B K,   ||w_e|| <= eta.

States whose flow is identically zero (e.g. a stance-foot position held within a domain)
keep a zero error and are left out. With A_cl Hurwitz and P > 0 solving the Lyapunov
equation A_cl^T P + P A_cl = -Q, the function V(e) = sqrt(e^T P e) has the paper's
linear-in-norm form (Definition iss_lyap):

* k1 ||e|| <= V <= k2 ||e||, k1 = sqrt(lambda_min(P)), k2 = sqrt(lambda_max(P));
* V' = (e^T P A_cl e + e^T P w_e) / V = (-e^T Q e / 2 + (P^1/2 e)^T (P^1/2 w_e)) / V
  <= -lambda_min(Q) ||e||^2 / (2 V) + ||P^1/2 w_e||   (Cauchy-Schwarz, ||P^1/2 e|| = V)
  <= -k3 ||e|| + sigma(eta),  k3 = lambda_min(Q) / (2 k2),  sigma(eta) = k2 eta
  (V <= k2 ||e|| gives ||e||^2 / V >= ||e|| / k2; ||P^1/2 w|| <= k2 ||w||).

Then gamma = k3 / k2 and a(t) = sigma / (gamma k1) (1 - e^{-gamma t}) bounds ||e(t)|| from
e(0) = 0 while e stays in the region of attraction. The ROA is *estimated*: the largest
level c such that the nonlinear, input-saturated error dynamics at the same nominal,
f(x~ + e, sat(u~ - K e)) - f(x~, u~), decreases V at every sample of {V <= c} outside a
small ball. tau is the first t with a(t) > c / k2 (the ball {||e|| <= a(t)} leaves
{V <= c}), infinity if a(inf) = sigma / (gamma k1) <= c / k2.

The paper's condition sigma(eta) / k1 <= eta reads k2 / k1 <= 1 here: it holds iff P is a
multiple of the identity (a symmetric A_cl + A_cl^T = -I / p); a(t) is a valid bound
whether it holds or not (the condition only makes a(t) <= eta t e^{L_x t}).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from hmpc_cli.core import signals
from hmpc_cli.core.hybrid import HybridSystem
from hmpc_cli.tube.sampling import TubeError, jacobians, num

__all__ = ["Certificate", "a_bound", "eiss_constants", "pd_certificate", "roa_level",
           "solve_lyapunov", "tau_of"]

_ROA_ROUNDS = 8
_SMALL = 1e-6  # samples with ||e|| below this are left out (round-off of f(x~ + e) - f(x~))


def solve_lyapunov(A: np.ndarray, Q: np.ndarray) -> np.ndarray:
    """P with A^T P + P A = -Q, shapes (n, n), by the vec form (I kron A^T + A^T kron I).

    Raises:
        TubeError: ("certificate") the equation is singular (A has eigenvalues summing to 0).
    """
    A, Q = np.atleast_2d(np.asarray(A, float)), np.atleast_2d(np.asarray(Q, float))
    n = A.shape[0]
    eye = np.eye(n)
    M = np.kron(eye, A.T) + np.kron(A.T, eye)
    try:
        vec = np.linalg.solve(M, -Q.reshape(-1, order="F"))
    except np.linalg.LinAlgError:
        raise TubeError("certificate", "the Lyapunov equation is singular") from None
    P = vec.reshape(n, n, order="F")
    return 0.5 * (P + P.T)


def eiss_constants(P: np.ndarray, Q: np.ndarray) -> tuple[float, float, float]:
    """(k1, k2, k3) of V = sqrt(e^T P e): sqrt(lambda_min P), sqrt(lambda_max P), lmin(Q)/(2 k2)."""
    lam = np.linalg.eigvalsh(P)
    k1, k2 = math.sqrt(lam[0]), math.sqrt(lam[-1])
    return k1, k2, float(np.linalg.eigvalsh(Q)[0]) / (2.0 * k2)


def a_bound(t, sigma: float, gamma: float, k1: float):
    """Prop. 3's a(t) = sigma / (gamma k1) (1 - e^{-gamma t}) (t [s], scalar or array)."""
    return sigma / (gamma * k1) * -np.expm1(-gamma * np.asarray(t, dtype=float))


def tau_of(level: float, k2: float, a_inf: float, gamma: float) -> float:
    """First t with a(t) > level / k2 (the tube leaves {V <= level}); inf if never."""
    r = level / k2
    if a_inf <= r:
        return math.inf
    return -math.log1p(-r / a_inf) / gamma


@dataclass(frozen=True)
class Certificate:
    """Prop. 3's certificate of the PD error dynamics, or why there is none.

    Attributes:
        certified: whether A_cl is Hurwitz (then the other fields are set).
        reason: why there is no certificate ('' if certified).
        mode: the mode linearised in; ``nominal_x``, ``nominal_u``: the nominal point.
        states: the error coordinates certified (names; zero-flow states left out).
        eigenvalues: of A_cl, as (real, imag) pairs.
        k1: sqrt(lambda_min(P)); ``k2``: sqrt(lambda_max(P)); ``k3``: lambda_min(Q)/(2 k2).
        sigma: sigma(eta) = k2 eta; ``gamma``: k3 / k2 [1/s]; ``a_inf``: sigma/(gamma k1).
        check: whether sigma / k1 <= eta (the paper's condition; here k2 / k1 <= 1).
        check_text: the check with its numbers.
        roa_level: the ROA estimate {V <= roa_level}; ``roa_radius`` = roa_level / k2,
            the largest ball inside it; ``roa_capped``: no violation up to the cap.
        roa_samples: closed-loop samples evaluated for the ROA.
        tau: first t with a(t) > roa_radius [s] (inf: never).
    """

    certified: bool
    reason: str
    mode: str
    nominal_x: tuple[float, ...]
    nominal_u: tuple[float, ...]
    states: tuple[str, ...] = ()
    eigenvalues: tuple[tuple[float, float], ...] = ()
    k1: float | None = None
    k2: float | None = None
    k3: float | None = None
    sigma: float | None = None
    gamma: float | None = None
    a_inf: float | None = None
    check: bool | None = None
    check_text: str = ""
    roa_level: float | None = None
    roa_radius: float | None = None
    roa_capped: bool = False
    roa_samples: int = 0
    tau: float = math.inf

    def a(self, t):
        """Prop. 3's bound on ||e(t)|| [state norm] (requires ``certified``)."""
        return a_bound(t, self.sigma, self.gamma, self.k1)

    def to_dict(self) -> dict:
        """JSON-ready dict (infinities as "inf")."""
        d = {k: getattr(self, k) for k in self.__dataclass_fields__}
        d["eigenvalues"] = [list(e) for e in self.eigenvalues]
        for k in ("k1", "k2", "k3", "sigma", "gamma", "a_inf", "roa_level", "roa_radius",
                  "tau"):
            d[k] = None if d[k] is None else num(d[k])
        return {**d, "nominal_x": list(self.nominal_x), "nominal_u": list(self.nominal_u),
                "states": list(self.states)}


def _nominal(system: HybridSystem) -> tuple[int, np.ndarray, np.ndarray, np.ndarray]:
    """(mode, x~, u~, u box) : x0 in the initial mode, u~ the box centre (clipped to it)."""
    i = system.mode_index(system.initial_mode)
    md = system.modes[i]
    lo, hi = np.array(md.u_lower, dtype=float), np.array(md.u_upper, dtype=float)
    u = np.clip(0.5 * (lo + hi), lo, hi)
    return i, system.x0.astype(float), u, np.array([lo, hi])


def pd_certificate(system: HybridSystem, kp: float, kd: float, eta: float,
                   samples: int = 2000, seed: int = 0, scale: float = 1.0) -> Certificate:
    """Prop. 3's certificate of u = u_ff + K (x_ref - x), K = system.tracking_gain(kp, kd).

    Linearises at x0 in the initial mode with u~ the input box's centre, solves the
    Lyapunov equation with Q = I and estimates the ROA by sampling (module docstring).

    Args:
        system: the hybrid system.
        kp: proportional gain of the low level.
        kd: derivative gain of the low level.
        eta: disturbance bound.
        samples: closed-loop samples per ROA round.
        seed: sampling seed.
        scale: a state-norm size (e.g. the region's diameter): the ROA search starts
            at the level k2 max(2 a(inf), scale).
    """
    jac = jacobians(system)
    i, x_nom, u_nom, ubox = _nominal(system)
    keep = [j for j in range(system.n_x) if j not in jac.static[i]]
    base = dict(mode=system.modes[i].name, nominal_x=tuple(x_nom.tolist()),
                nominal_u=tuple(u_nom.tolist()),
                states=tuple(system.state_names[j] for j in keep))
    A, B, _ = (m[0] for m in jac(i, x_nom[None], u_nom[None]))
    K = np.atleast_2d(np.asarray(system.tracking_gain(kp, kd), dtype=float))
    if not (np.all(np.isfinite(A)) and np.all(np.isfinite(B))):
        return Certificate(False, "the linearisation at x0 is not finite", **base)
    A_cl = (A - B @ K)[np.ix_(keep, keep)]
    eig = np.linalg.eigvals(A_cl)
    pairs = tuple((float(e.real) + 0.0, float(e.imag) + 0.0) for e in eig)
    worst = float(eig.real.max()) if eig.size else -math.inf
    tol = 1e-9 * max(1.0, float(np.abs(A_cl).max()))  # round-off of the eigenvalues
    if not eig.size or worst >= -tol:
        why = " with no low-level feedback (kp = kd = 0)" if not np.any(K) else ""
        within = (f", not below -{tol:.3g} (1e-9 x the largest |entry| of A - B K: zero "
                  "within round-off)") if worst < 0.0 else ""
        return Certificate(False, f"A - B K linearised at x0 in mode {base['mode']!r} is not "
                           f"Hurwitz{why}: largest eigenvalue real part {worst + 0.0:.4g}"
                           f"{within} (eigenvalues {_fmt_eigs(eig)})", eigenvalues=pairs,
                           **base)
    Q = np.eye(len(keep))
    P = solve_lyapunov(A_cl, Q)
    k1, k2, k3 = eiss_constants(P, Q)
    sigma, gamma = k2 * eta, k3 / k2
    a_inf = sigma / (gamma * k1)
    closed = _ClosedLoop(jac, i, x_nom, u_nom, ubox, K, keep, P)
    level, capped, count = roa_level(closed, P, k2 * max(2.0 * a_inf, scale), samples, seed)
    check = sigma / k1 <= eta * (1 + 1e-12)
    text = (f"sigma/k1 = {sigma / k1:.4g} {'<=' if check else '>'} eta = {eta:.4g} "
            f"(k2/k1 = {k2 / k1:.4g})")
    return Certificate(True, "", eigenvalues=pairs, k1=k1, k2=k2, k3=k3, sigma=sigma,
                       gamma=gamma, a_inf=a_inf, check=bool(check), check_text=text,
                       roa_level=level, roa_radius=level / k2, roa_capped=capped,
                       roa_samples=count, tau=tau_of(level, k2, a_inf, gamma), **base)


def _fmt_eigs(eig: np.ndarray) -> str:
    """Up to six eigenvalues as text."""
    shown = [f"{e.real + 0.0:.3g}{e.imag:+.3g}j" if abs(e.imag) > 1e-12 else
             f"{e.real + 0.0:.3g}" for e in eig[:6]]
    return ", ".join(shown) + (", ..." if len(eig) > 6 else "")


class _ClosedLoop:
    """V' of the nonlinear, saturated error dynamics at the nominal point (batched)."""

    def __init__(self, jac, mode: int, x_nom, u_nom, ubox, K, keep, P) -> None:
        self.flow, self.x_nom, self.u_nom, self.ubox = jac.flows[mode], x_nom, u_nom, ubox
        self.K, self.keep, self.P = K[:, keep], keep, P
        self.n_w = jac.system.n_w
        self.f_nom = self.flow(x_nom, u_nom, np.zeros(self.n_w))[0][keep]

    def vdot(self, e: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(V'(e), V(e)) for errors e (B, r) in the kept coordinates."""
        x = np.repeat(self.x_nom[None], len(e), 0)
        x[:, self.keep] += e
        u = np.clip(self.u_nom - e @ self.K.T, self.ubox[0], self.ubox[1])
        de = self.flow(x, u, np.zeros(self.n_w))[0][:, self.keep] - self.f_nom
        Pe = e @ self.P
        V = np.sqrt(np.einsum("bi,bi->b", Pe, e))
        return np.einsum("bi,bi->b", Pe, de) / V, V


def roa_level(closed: _ClosedLoop, P: np.ndarray, cap: float, samples: int,
              seed: int) -> tuple[float, bool, int]:
    """Largest c with V' < 0 at every sample of {V <= c} (||e|| >= 1e-6): (c, capped, count).

    Starts at ``cap``. Each of 8 rounds samples {V <= c} at ``samples`` errors (uniform
    directions; V levels half uniform in [0, c], half uniform in log between the least V
    of an error of norm 1e-6 and c, so that a cap decades above where V' turns positive is
    sampled at every scale) and lowers c to the smallest V where V' >= 0. Every round runs
    (a round that finds none is checked by the next): ``capped`` when none ever did.
    """
    if not cap > 0.0:  # nothing to sample: the level 0, as far as it goes
        return 0.0, True, 0
    rng = np.random.default_rng(seed)
    L_inv_T = np.linalg.inv(np.linalg.cholesky(P)).T  # V(L^-T z) = ||z||
    floor = math.sqrt(float(np.linalg.eigvalsh(P).min())) * _SMALL  # V >= k1 ||e||
    c, count = cap, 0
    for _ in range(_ROA_ROUNDS):
        signals.check()  # a stop signal ends the sampling between rounds
        z = rng.standard_normal((samples, P.shape[0]))
        level = rng.uniform(0.0, 1.0, samples)  # V / c
        level[1::2] = np.exp(rng.uniform(math.log(min(floor, c) / c), 0.0, samples // 2))
        z *= (level / np.linalg.norm(z, axis=1))[:, None]
        e = c * z @ L_inv_T.T
        e = e[np.linalg.norm(e, axis=1) >= _SMALL]
        if not len(e):
            break
        vdot, V = closed.vdot(e)
        count += len(e)
        bad = ~(vdot < 0.0)
        if np.any(bad):
            c = float(V[bad].min())
    return float(c), c == cap, count
