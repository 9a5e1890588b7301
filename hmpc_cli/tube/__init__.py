"""Tracking-error tubes of the paper's Section III-B: constants, bounds, margins.

Pure mathematics on a :class:`~hmpc_cli.core.hybrid.HybridSystem` and plain settings values
(never a Scenario). Notation (Euclidean norms; the tracking error is e = x - x_ref):

* L_x, L_u: Lipschitz constants of the flows, *estimated* as the sampled maximum of
  ||df/dx||_2 and ||df/du||_2 over a state box (:class:`Region`) and each mode's input
  box, w = 0 (:mod:`.sampling`): estimates, never certificates.
* eta >= ||f_plant(x, u, w) - f(x, u, 0)|| over the box of w: what w adds to the flow
  plus, when the simulated plant is another system than the model f (a scenario's
  ``[plant]``), the sampled mismatch of the two flows at w = 0.
* zeta >= ||u - u_ff||, what the low level u = u_ff + K (x_ref - x) adds (:mod:`.bounds`).
* The trivial tube (Prop. 2) (eta + L_u zeta) t e^{L_x t}; feed-forward only (its
  Remark) eta t e^{L_x t}; Prop. 3's a(t) from an E-ISS Lyapunov function of the PD error
  dynamics, valid until tau (:mod:`.certificate`).
* diam T(dt), dt the MPC period, is the planning tube; :func:`margins` turns a radius into
  the guard-avoid, virtual-node and input-box tightenings of problem (14) (:mod:`.report`
  tabulates them per MPC rate).
"""

from hmpc_cli.tube.bounds import (
    GuardMargin, InputMargin, Margins, feedforward_tube, initial_violations,
    input_box_diameter, low_level_share, margins, trivial_tube, zeta_bound)
from hmpc_cli.tube.certificate import (
    Certificate, a_bound, eiss_constants, pd_certificate, roa_level, solve_lyapunov, tau_of)
from hmpc_cli.tube.report import (
    DEFAULT_RATES, TubeReport, TubeRow, analyse, diameter_curves, tube_row)
from hmpc_cli.tube.sampling import (
    ESTIMATE_NOTE, DisturbanceBound, LipschitzEstimate, Region, TubeError, eta_bound,
    lipschitz, region_from_scenario)

__all__ = [
    "DEFAULT_RATES", "ESTIMATE_NOTE", "Certificate", "DisturbanceBound", "GuardMargin",
    "InputMargin", "LipschitzEstimate", "Margins", "Region", "TubeError", "TubeReport",
    "TubeRow", "a_bound", "analyse", "diameter_curves", "eiss_constants", "eta_bound",
    "feedforward_tube", "initial_violations", "input_box_diameter", "lipschitz",
    "low_level_share", "margins", "pd_certificate", "region_from_scenario", "roa_level",
    "solve_lyapunov", "tau_of", "trivial_tube", "tube_row", "zeta_bound",
]
