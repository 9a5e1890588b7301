"""Biped benchmarks: walking-MPC solve times and the foothold planning step.

Run on demand:  python benchmarks/bench_biped.py [--duration S] [--mass-scale F]

1. NLP build time and one cold solve from the reference initial state (segment 1).
2. A closed-loop walk on the Figure 4 course: HybridSimulator on ``build_biped`` (links
   ``--mass-scale`` heavier than the planning model), the PD + feed-forward low level
   (Kp 700, Kd 10) at ``--sim-hz``, the MPC re-solved every 0.1 s (warm, the chosen
   segment) and right after each contact (planning step: every candidate segment, the
   largest final hip x kept). At a contact the step is cut at the first event (the
   simulator holds the input across a reset, and the pre-impact torque on the relabelled
   legs would push the new swing foot straight back into the ground).

Prints medians, p95 and the ratio to the target (warm MPC median <= 100 ms). Timing is
measured, never asserted.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from hmpc_cli.lowlevel import LowLevelController, LowLevelSettings
from hmpc_cli.mpc.walking import WalkingMPC, WalkingMPCSettings
from hmpc_cli.planner.footholds import candidates, choose
from hmpc_cli.sim import HybridSimulator
from hmpc_cli.systems.biped import BipedParams, build_biped

TARGET = 0.100


def stats(name: str, v: list[float], target: float | None = None) -> None:
    a = np.asarray(v) * 1e3
    if a.size == 0:
        print(f"{name:<34} (none)")
        return
    line = (f"{name:<34} n={a.size:3d}  median {np.median(a):7.1f} ms  "
            f"p95 {np.percentile(a, 95):7.1f} ms  max {a.max():7.1f} ms")
    if target is not None:
        line += f"  median/target {np.median(a) / (1e3 * target):.2f}"
    print(line)


def plan_step(mpc: WalkingMPC, t: float, x: np.ndarray):
    """Every candidate from x, best kept: (plan or None, wall time, candidates, plans)."""
    start = time.perf_counter()
    cand = candidates(float(x[10]), mpc.segments)
    plans = mpc.solve_candidates(t, x, cand, 0.0)
    best = choose(plans)
    wall = time.perf_counter() - start
    return (plans[best] if best is not None else None), wall, cand, plans


def walk(duration: float, mass_scale: float, sim_hz: int) -> None:
    p = BipedParams()
    start = time.perf_counter()
    mpc = WalkingMPC(p, WalkingMPCSettings())
    print(f"NLP build: {time.perf_counter() - start:.2f} s "
          f"({mpc.nlp.nw} variables, {mpc.nlp.ng} constraints)")
    plant = build_biped(p.model_copy(update={"mass_scale": mass_scale}))
    cold = WalkingMPC(p, mpc.s, nlp=mpc.nlp).solve(0.0, plant.x0, 1, 0.0)
    print(f"cold solve from x0, segment 1: {cold.stats.wall_time * 1e3:.0f} ms, "
          f"{cold.stats.iterations} iterations, {cold.stats.status}")
    sim = HybridSimulator(plant, max_events=1000)
    low = LowLevelController(plant, LowLevelSettings(kp=700.0, kd=10.0))
    x, t, t_contact, dt = plant.x0.copy(), 0.0, 0.0, 1.0 / sim_hz
    warm, iters, steps = [], [], []
    plan, wall, cand, plans = plan_step(mpc, t, x)
    first = wall
    print(f"t=0.000 candidates {cand}: chose segment {plan.extra['segment']}")
    next_solve = 0.1
    failures = 0
    while t < duration - 1e-9:
        u, _ = low.command(t, x, plan)
        r = sim.step(x[None], np.zeros(1, int), u[None], np.zeros((1, 1)), dt,
                     raise_zeno=False)
        if r.events:
            ev = r.events[0]
            t, x = t + ev.tau, ev.x_after.copy()
            t_contact = t
            mpc.on_impact(plan.extra["segment"])
            new, wall, cand, plans = plan_step(mpc, t, x)
            steps.append(wall)
            iters_c = [q.stats.iterations for q in plans]
            print(f"t={t:.3f} contact {plant.guards[ev.guard].name} at x={x[10]:.3f}: "
                  f"candidates {cand} iterations {iters_c}, planning step "
                  f"{wall * 1e3:.0f} ms -> segment "
                  f"{new.extra['segment'] if new else 'none (kept)'}")
            plan = new or plan
            next_solve = t + 0.1
            continue
        t, x = t + dt, r.x[0]
        if t >= next_solve - 1e-9:
            new = mpc.solve(t, x, plan.extra["segment"], t - t_contact)
            warm.append(new.stats.wall_time)
            iters.append(new.stats.iterations)
            if new.stats.success:
                plan = new
            else:
                failures += 1
            next_solve += 0.1
    hip = np.asarray(plant.goal_map(x)).ravel()
    print(f"end t={t:.2f} s: hip ({hip[0]:.3f}, {hip[1]:.3f}), goal {p.goal}, "
          f"warm failures {failures}")
    print()
    stats("warm re-solve (10 Hz)", warm, TARGET)
    print(f"{'':<34} iterations median {np.median(iters):.0f}, max {max(iters)}")
    print(f"{'planning step at t = 0 (cold)':<34} {first * 1e3:7.1f} ms")
    stats("planning step after a contact", steps)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--duration", type=float, default=2.5, help="simulated time [s]")
    ap.add_argument("--mass-scale", type=float, default=1.1, help="plant mass factor")
    ap.add_argument("--sim-hz", type=int, default=1000, help="simulator rate [Hz]")
    args = ap.parse_args()
    walk(args.duration, args.mass_scale, args.sim_hz)


if __name__ == "__main__":
    main()
