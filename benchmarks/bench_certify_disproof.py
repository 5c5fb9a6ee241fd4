"""`dj.certify` of controllers that are NOT dissipative: the cheap disproof against the SDP.

For each order, two random non-passive controllers (m = p = 2, passivity): an unstable one
(spectral radius 1.2) and a stable one whose response leaves the rate at some frequency
(He G(e^{jw}) < 0 there, D = I). Times `dj.certify` (which disproves them without the SDP)
and, in the same run, the maximum-margin SDP alone (`certify_sdp.solve`, what `certify`
ran for such controllers before), and prints the ratio. The SDP is skipped above
`--sdp-max` (minutes at n = 48).

Usage: OPENBLAS_NUM_THREADS=1 python benchmarks/bench_certify_disproof.py [--orders 6 12 24 48]
"""

import argparse
import time

import numpy as np

import dissil_jax as dj
from dissil_jax.internal import certify_sdp


def _controllers(n, seed=0):
    rng = np.random.default_rng(seed)
    A = rng.normal(size=(n, n))
    A /= max(abs(np.linalg.eigvals(A)))
    B, C = rng.normal(size=(n, 2)), rng.normal(size=(2, n))
    return {"unstable": (1.2 * A, B, C, np.eye(2)), "frequency": (0.9 * A, B, C, np.eye(2))}


def main(orders, sdp_max):
    qsr = dj.QSR.passive(2)
    print("| n | controller | certify (s) | verdict | SDP alone (s) | SDP / certify |")
    print("|---:|---|---:|---|---:|---:|")
    for n in orders:
        for label, mats in _controllers(n).items():
            K = dj.LTIController(*mats)  # built outside the timer (its checks compile once)
            t = time.perf_counter()
            cert = dj.certify(K, qsr)
            t_cert = time.perf_counter() - t
            assert not cert.holds
            row = f"| {n} | {label} | {t_cert:.4f} | {cert.source} |"
            if n <= sdp_max:
                t = time.perf_counter()
                P, status = certify_sdp.solve(*mats, qsr)
                t_sdp = time.perf_counter() - t
                row += f" {t_sdp:.3f} ({status}) | {t_sdp / t_cert:.0f}x |"
            else:
                row += " (skipped) | |"
            print(row, flush=True)


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--orders", type=int, nargs="+", default=[6, 12, 24, 48])
    parser.add_argument("--sdp-max", type=int, default=24)
    args = parser.parse_args()
    main(args.orders, args.sdp_max)
