"""ICO speed: seconds per iteration against a cvxpy-built reference of the same SDP.

For N windows of the paper's linear-example sizes (n = 6, m = p = 3, passive supply rate,
synthetic random data), measures in one run:

- `ours`: one full ICO iteration (SDP data assembly in numpy, Clarabel in-place update and
  solve, float64 loss and KYP re-check of the new iterate), averaged over the first
  iterations of one run;
- `cvxpy`: the same SDP (same variables, cones and objective) written in cvxpy with one
  constraint per window, built and solved with Clarabel at the same iterates;
- the ratio, the agreement of the two optimal values, and the growth with N;
- `fit_ico`: wall time of `dj.fit_ico` with 2 initialisations on 2 threads (max 150 steps,
  tol 1e-3, the paper's settings), and the implied time per controller.

The paper reports 28 s (2 windows) to 2,760 s (200 windows) per ICO controller for this
problem. The machine is shared and noisy: read ratios, not absolute times.

Usage: python benchmarks/bench_ico.py [--quick]
"""

import argparse
import os
import sys
import time

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import cvxpy as cp  # noqa: E402
import jax  # noqa: E402
import jax.random as jr  # noqa: E402
import numpy as np  # noqa: E402

jax.config.update("jax_enable_x64", True)

import dissil_jax as dj  # noqa: E402
from dissil_jax.internal import (  # noqa: E402
    ICOProblem,
    ICOSolver,
    ico_run,
    single_threaded_blas,
    stacked_factor,
)

# The synthetic expert data are shared with the ICO tests.
sys.path.insert(0, os.path.join(os.path.dirname(__file__), os.pardir, "tests"))
from helpers import expert_windows  # noqa: E402

PAPER = {2: 28.0, 25: None, 100: None, 200: 2760.0}  # s per ICO controller (paper §5.1)


def synthetic_windows(N, n=6, p=3, m=3, seed=0):
    """Two-step windows of a random LTI expert plus noise (sizes of the linear example)."""
    return expert_windows(seed, n, p, m, N=N)


def cvxpy_step(pb: ICOProblem, theta0, P_tilde, w_tilde, eps, stacked=False):
    """The ICO SDP of `dissil_jax/_train/ico/sdp.py` written in cvxpy; returns (obj, time, status).

    `stacked=False`: one constraint per window (the direct formulation, window_cone='soc');
    `stacked=True`: the library's default QR-compressed single cone (window_cone='stacked'),
    with the factorisation done in numpy inside the timed region.
    """
    t_start = time.perf_counter()
    n, p, m, N = pb.n, pb.p, pb.m, pb.N
    A0, B0, C0, D0 = pb.mats(theta0)
    dA, dB = cp.Variable((n, n)), cp.Variable((n, p))
    dC, dD = cp.Variable((m, n)), cp.Variable((m, p))
    P = cp.Variable((n, n), symmetric=True)
    y, w, tau = cp.Variable(), cp.Variable(), cp.Variable()
    sig = cp.Variable(N)
    A, B, C, D = A0 + dA, B0 + dB, C0 + dC, D0 + dD
    S, R = pb.qsr.S, pb.qsr.R
    L = pb.qsr.neg_q_factor()
    assert L.shape[1] == 0, "reference written for Q = 0"
    Pt = P_tilde
    M = cp.bmat([
        [-P, -C.T @ S, (Pt @ A).T],
        [-(C.T @ S).T, -D.T @ S - S.T @ D - R, (Pt @ B).T],
        [Pt @ A, Pt @ B, P - 2 * Pt],
    ])
    E = np.eye(2 * n + p)
    E[-n:, -n:] = Pt @ Pt
    # The same balancing congruence diag(P~^-1/2, I, P~^-1/2) as the library (ICOProblem).
    lam, V = np.linalg.eigh(Pt)
    T = np.eye(2 * n + p)
    T[:n, :n] = T[-n:, -n:] = (V / np.sqrt(lam)) @ V.T
    M = T @ ((M + M.T) / 2) @ T
    cons = [(M + M.T) / 2 << -eps * (T @ E @ T)]
    dAB = cp.hstack([dA, dB])
    cons.append(cp.quad_over_lin(dAB @ pb.F, w) <= tau)
    phi = 2 / w_tilde - w / w_tilde**2
    cons.append(cp.bmat([[y * np.eye(m), dC], [dC.T, phi * np.eye(n)]]) >> 0)
    z = pb.x0 @ A0.T + pb.u0 @ B0.T
    theta = cp.hstack([cp.vec(dA, order="C"), cp.vec(dB, order="C"), cp.vec(dC, order="C"),
                       cp.vec(dD, order="C")])
    if stacked:
        R, g, c = stacked_factor(pb, C0, z, pb.t1 - z @ C0.T - pb.u1 @ D0.T)
        cons.append(cp.quad_over_lin(cp.hstack([g - R @ theta, np.array([c])]), 1 - y)
                    <= cp.sum(sig))
    else:
        for k in range(N):  # one constraint per window, as a direct cvxpy formulation would
            dz = dA @ pb.x0[k] + dB @ pb.u0[k]
            ebar = pb.t1[k] - C0 @ z[k] - D0 @ pb.u1[k] - C0 @ dz - dC @ z[k] - dD @ pb.u1[k]
            cons.append(cp.quad_over_lin(ebar, 1 - y) <= sig[k])
    r0 = pb.t0 - pb.x0 @ C0.T - pb.u0 @ D0.T - pb.x0 @ dC.T - pb.u0 @ dD.T
    iu = np.triu_indices(n)
    obj = (pb.c * (cp.sum_squares(r0) + tau + cp.sum(sig)) + pb.prox / 2 * cp.sum_squares(theta)
           + pb.reg / 2 * cp.sum_squares(cp.hstack([P[i, j] - Pt[i, j] for i, j in zip(*iu)])))
    prob = cp.Problem(cp.Minimize(obj), cons)
    try:
        prob.solve(solver=cp.CLARABEL)
    except cp.SolverError:
        return np.nan, time.perf_counter() - t_start, "solver error"
    return prob.value, time.perf_counter() - t_start, prob.status


def _iteration(pb, solver, theta, P, w, qsr):
    """One full ICO iteration as `fit_ico` does it; returns (step results, seconds)."""
    t0 = time.perf_counter()
    eps = min(pb.eps, (1 - 1e-3) * pb.kyp_margin(theta, P))
    d, P_new, w_new, status, _ = solver.solve(theta, P, w, eps)
    pb.loss(theta + d)
    dj.internal.kyp_certified(*pb.mats(theta + d), qsr, P_new)
    return (d, P_new, w_new, eps), time.perf_counter() - t0


def bench(N, iters, ref_iters, run_fit):
    qsr = dj.QSR.passive(3)
    windows = synthetic_windows(N)
    data = (np.asarray(windows.x0), np.asarray(windows.y), np.asarray(windows.target))
    pb = ICOProblem(*data, qsr)  # the default, window_cone="stacked"
    pb_win = ICOProblem(*data, qsr, window_cone="soc")
    K = dj.LTIController.random(jr.PRNGKey(N), 6, 3, 3, scale=0.1)
    K, P = dj.project(K, qsr)
    theta, P = pb.theta(K.A, K.B, K.C, K.D), np.asarray(P)
    solver, solver_win = ICOSolver(pb), ICOSolver(pb_win)
    w = ico_run._young_scale(pb, theta)
    t = {k: [] for k in ("ours", "ours_win", "cvxpy_win", "cvxpy_stacked")}
    gaps = []
    with single_threaded_blas():
        for it in range(iters):
            (d, P_new, w_new, eps), seconds = _iteration(pb, solver, theta, P, w, qsr)
            t["ours"].append(seconds)
            t["ours_win"].append(_iteration(pb_win, solver_win, theta, P, w, qsr)[1])
            if it < ref_iters:
                # our obj_val omits the constants c*sum||r0||^2 and reg/2*||P~||^2
                C0, D0 = pb.mats(theta)[2:]
                const = pb.c * np.sum((pb.t0 - pb.x0 @ C0.T - pb.u0 @ D0.T) ** 2)
                const += pb.reg / 2 * np.sum(P[np.triu_indices(6)] ** 2)
                for name, stacked in (("cvxpy_win", False), ("cvxpy_stacked", True)):
                    obj_ref, t_ref, _ = cvxpy_step(pb, theta, P, w, eps, stacked=stacked)
                    t[name].append(t_ref)
                    gaps.append(abs(solver.obj_val + const - obj_ref) / max(1.0, abs(obj_ref)))
                gaps.append(abs(solver.obj_val - solver_win.obj_val)
                            / max(1.0, abs(solver_win.obj_val + const)))
            theta, P = theta + d, (P_new + P_new.T) / 2
            w = float(np.clip(w_new, w / 4, 2 * w))
    row = dict(N=N, gap=np.nanmax(gaps + [np.nan]), **{k: np.median(v) for k, v in t.items()})
    if run_fit:
        res = dj.fit_ico(jr.PRNGKey(1), windows, qsr, num_inits=2, max_steps=150, atol=1e-3)
        row["fit"] = float(res.wall_time)
        row["steps"] = np.asarray(res.steps).tolist()
        row["certified"] = bool(np.all(np.asarray(res.certified)))
    return row


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="N in {2, 25}, fewer iterations")
    args = parser.parse_args()
    sizes = [2, 25] if args.quick else [2, 25, 100, 200]
    iters, ref_iters = (4, 2) if args.quick else (10, 3)
    dj.fit_ico_nc(jr.PRNGKey(0), synthetic_windows(2), num_inits=1, max_steps=1)  # warm-up
    rows = [bench(N, iters, ref_iters, run_fit=not args.quick) for N in sizes]
    print("ICO, n=6, m=p=3, passive; seconds per iteration (median)")
    head = (f"{'N':>5} {'ours':>8} {'ours/win':>9} {'cvxpy/win':>10} {'cvxpy/stk':>10}"
            f" {'win/ours':>9} {'stk/ours':>9} {'obj gap':>8}")
    if not args.quick:
        head += f" {'fit_ico 2 inits':>16} {'steps':>10} {'paper':>7}"
    print(head)
    for r in rows:
        line = (f"{r['N']:>5} {r['ours']:>8.4f} {r['ours_win']:>9.4f} {r['cvxpy_win']:>10.4f}"
                f" {r['cvxpy_stacked']:>10.4f} {r['cvxpy_win'] / r['ours']:>8.1f}x"
                f" {r['cvxpy_stacked'] / r['ours']:>8.1f}x {r['gap']:>8.0e}")
        if "fit" in r:
            paper = PAPER.get(r["N"])
            line += (f" {r['fit']:>15.1f}s {str(r['steps']):>10}"
                     f" {'' if paper is None else f'{paper:.0f}s':>7}")
        print(line)
    base = rows[0]
    print(f"growth of s/iteration with N (relative to N = {base['N']}):")
    for r in rows[1:]:
        print(f"  N={r['N']:>3}: ours x{r['ours'] / base['ours']:.1f}, per-window ours "
              f"x{r['ours_win'] / base['ours_win']:.1f}, cvxpy per-window "
              f"x{r['cvxpy_win'] / base['cvxpy_win']:.1f}  (N ratio x{r['N'] / base['N']:.0f})")


if __name__ == "__main__":
    main()
