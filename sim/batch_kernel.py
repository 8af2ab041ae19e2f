"""The compiled inner loop of :func:`sim.batch.simulate_batch` (``engine="numba"``).

One run at a time, every tick of it with the state in registers, the runs of a chunk spread
over the cores (``numba.prange``).  The arithmetic is the numpy reference's
(:func:`sim.batch._loop_numpy`), operation for operation, so that a run's metrics and traces
are **bit-identical** to the reference's (``tests/test_batch_kernel.py`` checks
``array_equal`` on hundreds of runs with delay, quantisation, noise and saturation):

* the same expression trees in the same order (IEEE arithmetic is not associative); compiled
  without ``fastmath`` so LLVM neither reassociates nor contracts ``a*b + c`` into an FMA;
* the controller's matrix product as a sequential sum over the columns, as the reference
  writes it (no BLAS, no einsum);
* ``sin``/``cos`` from the C library (numba lowers ``math.sin`` to libm's), the same functions
  numpy's ``np.sin``/``np.cos`` call where numpy has no vectorised version of its own for
  float64 -- :func:`numpy_trig_is_libm` checks that on the machine (true on x86-64 without
  AVX-512, where numpy has none; with AVX-512 numpy may use its own SIMD sin/cos and the
  engines can then differ in the last bit);
* numpy's NaN-propagating ``maximum``/``clip`` and round-half-even ``rint``;
* the noise drawn by the same per-run generators before the kernel runs (not in it).

The compiled code is cached on disk (``cache=True``: ``sim/__pycache__``), so only the first
use on a machine pays the compilation (~10 s).
"""

from __future__ import annotations

import math

import numpy as np

try:  # numba is optional: without it simulate_batch uses the numpy reference
    import numba
    from numba import njit, prange

    AVAILABLE = True
except ImportError:  # pragma: no cover - exercised only without numba
    numba = None
    AVAILABLE = False

__all__ = ["AVAILABLE", "run_chunk", "numpy_trig_is_libm", "threads"]

ENC_MODULUS = 1 << 16
LANES = 4  # runs advanced side by side in the kernel
DUTY_MAX = 32767.0


def numpy_trig_is_libm(n: int = 4096, seed: int = 7) -> bool:
    """True if ``np.sin``/``np.cos`` give exactly ``math.sin``/``math.cos`` (libm) on this machine.

    The condition under which the compiled kernel is bit-identical to the numpy reference.
    """
    rng = np.random.default_rng(seed)
    x = np.concatenate([rng.standard_normal(n) * s for s in (0.01, 0.3, 2.0, 50.0)])
    s, c = np.sin(x), np.cos(x)
    return all(s[i] == math.sin(v) and c[i] == math.cos(v) for i, v in enumerate(x.tolist()))


def threads() -> int:
    """Threads the kernel runs on (numba's, ``NUMBA_NUM_THREADS``); 1 without numba."""
    return int(numba.get_num_threads()) if AVAILABLE else 1


if AVAILABLE:

    @njit(cache=True)
    def _max(a: float, b: float) -> float:
        # numpy's maximum: the first argument if it is NaN or >= the second, else the second
        return a if (a >= b or a != a) else b

    @njit(cache=True)
    def _clip(a: float, lo: float, hi: float) -> float:
        # numpy's clip: min(max(a, lo), hi) with NaN kept
        if a != a:
            return a
        v = a if a > lo else lo
        return v if (v < hi or v != v) else hi

    @njit(cache=True)
    def _xddot(F, xd, phid, s, c, Mm, J, mL, b, g):  # noqa: ANN001, ANN202
        # sim.plant.dynamics' xddot, term for term
        rhs1 = F - b * xd - mL * phid * phid * s
        rhs2 = mL * g * s
        mLc = mL * c
        det = Mm * J - mLc * mLc
        return (J * rhs1 + mLc * rhs2) / det

    @njit(cache=True)
    def _rhs(x1, x2, x3, duty, us, motor, fpa, Vs, R, kt, gear, rw, Mm, J, mL, b, g, accel, al):  # noqa: ANN001, ANN202
        # the reference's rhs(): force of the true motor (or us), the acceleration clip,
        # then sim.plant.dynamics -> (xddot, phiddot, F)
        if motor:
            d = _clip(duty, -DUTY_MAX, DUTY_MAX)
            V = d / DUTY_MAX * Vs
            w = gear * x1 / rw
            F = fpa * ((V - kt * w) / R)
        else:
            F = us
        s = math.sin(x2)
        c = math.cos(x2)
        if accel:
            a0 = _xddot(0.0, x1, x3, s, c, Mm, J, mL, b, g)
            a1 = _xddot(1.0, x1, x3, s, c, Mm, J, mL, b, g) - a0
            F = _clip(F, (-al - a0) / a1, (al - a0) / a1)
        rhs1 = F - b * x1 - mL * x3 * x3 * s
        rhs2 = mL * g * s
        mLc = mL * c
        det = Mm * J - mLc * mLc
        xdd = (J * rhs1 + mLc * rhs2) / det
        phidd = (mLc * rhs1 + Mm * rhs2) / det
        return xdd, phidd, F

    @njit(cache=True, parallel=True, nogil=True)
    def run_chunk(  # noqa: PLR0913, PLR0915
        n_ticks, sub, h, w0, band,
        X0, x_ref, delay, noise, noisy,
        Mm, J, mL, b, g,
        fpa, Vs, R, kt, gear, rw,
        motor, fpa_n, Vs_n, R_n, kt_n, gear_n, rw_n,
        cpm_p, cpr_p, off_p, full_p, cpm_f, cpr_f, off_f,
        G, Bu, u_max, gidx,
        accel, al,
        phi_max, x_max, xdd_max, f_max, last_out, phi_sq, f_sq,
        record, tr,
    ):  # noqa: ANN001
        """Simulate the runs of one chunk (arrays of length ``N`` = the chunk's runs).

        ``G`` (nz+2, nz+3, NG), ``Bu`` (nz, NG), ``u_max`` (NG,): the linear part of each
        controller, ``gidx`` (N,) the controller of each run.  ``noise`` (N, T, 2) when
        ``noisy``.  Outputs: the metric accumulators (N,) and, with ``record``, ``tr``
        (9, T, N) = x, xdot, phi, phidot, u_sat, force, duty, x_meas, phi_meas.

        The runs go in groups of ``LANES``, advanced together step by step: each run is a
        long chain of dependent operations (sin -> det -> division -> next RK4 stage), and
        independent chains side by side keep the core busy.  Every run's arithmetic is its
        own, in the reference's order.
        """
        N = X0.shape[0]
        nz = Bu.shape[0]
        nw = nz + 3
        hh = 0.5 * h
        h6 = h / 6.0
        K = LANES
        Lmax = 1
        for i in range(N):
            Lmax = max(Lmax, delay[i] + 1)
        ngroups = (N + K - 1) // K
        for grp in prange(ngroups):
            i0 = grp * K
            nl = min(K, N - i0)
            x0 = np.empty(K)
            x1 = np.empty(K)
            x2 = np.empty(K)
            x3 = np.empty(K)
            ring_e = np.empty((K, Lmax), np.int64)
            ring_a = np.empty((K, Lmax), np.int64)
            enc_last = np.empty(K, np.int64)
            enc_total = np.empty(K, np.int64)
            W = np.zeros((K, nw))
            out = np.empty((K, nz + 2))
            pm = np.empty(K)
            xm = np.empty(K)
            am = np.zeros(K)
            fm = np.zeros(K)
            lo = np.empty(K, np.int64)
            psq = np.zeros(K)
            fsq = np.zeros(K)
            duty = np.zeros(K)
            us = np.empty(K)
            k1 = np.empty((K, 4))
            k2 = np.empty((K, 4))
            k3 = np.empty((K, 4))
            k4 = np.empty((K, 4))
            Fk = np.empty(K)
            for l in range(nl):
                i = i0 + l
                x0[l], x1[l], x2[l], x3[l] = X0[i, 0], X0[i, 1], X0[i, 2], X0[i, 3]
                e0 = np.int64(np.rint((x0[l] + 0.0) * cpm_p)) % ENC_MODULUS
                a0 = np.int64(_clip(np.rint(off_p + (x2[l] + 0.0) * cpr_p), 0.0, full_p))
                for q in range(delay[i] + 1):
                    ring_e[l, q] = e0
                    ring_a[l, q] = a0
                enc_last[l] = e0
                dd = e0 % ENC_MODULUS
                enc_total[l] = dd - ENC_MODULUS if dd >= ENC_MODULUS // 2 else dd
                W[l, nz + 2] = x_ref[i]
                pm[l] = abs(x2[l])
                xm[l] = abs(x0[l])
                lo[l] = 0 if pm[l] > band else -1
            sample = 0
            for k in range(n_ticks + 1):
                for l in range(nl):
                    i = i0 + l
                    gi = gidx[i]
                    Lr = delay[i] + 1
                    # --- sensors: this tick's reading enters the delay line, the delayed one leaves
                    nx = noise[i, k, 0] if noisy else 0.0
                    nphi = noise[i, k, 1] if noisy else 0.0
                    ring_e[l, k % Lr] = np.int64(np.rint((x0[l] + nx) * cpm_p)) % ENC_MODULUS
                    ring_a[l, k % Lr] = np.int64(_clip(np.rint(off_p + (x2[l] + nphi) * cpr_p), 0.0, full_p))
                    seen_e = ring_e[l, (k - delay[i]) % Lr]
                    seen_a = ring_a[l, (k - delay[i]) % Lr]
                    dd = (seen_e - enc_last[l]) % ENC_MODULUS
                    enc_total[l] = enc_total[l] + (dd - ENC_MODULUS if dd >= ENC_MODULUS // 2 else dd)
                    enc_last[l] = seen_e
                    W[l, nz] = enc_total[l] / cpm_f
                    W[l, nz + 1] = (float(seen_a) - off_f) / cpr_f
                    # --- controller: rows [u; xdot_est; z'] = G [z; v], summed column by column
                    for r in range(nz + 2):
                        acc = G[r, 0, gi] * W[l, 0]
                        for j in range(1, nw):
                            acc = acc + G[r, j, gi] * W[l, j]
                        out[l, r] = acc
                    umax = u_max[gi]
                    u = _clip(out[l, 0], -umax, umax)
                    us[l] = u
                    if motor:
                        ii = u / fpa_n
                        w = gear_n * out[l, 1] / rw_n
                        V = ii * R_n + kt_n * w
                        duty[l] = float(np.int64(_clip(np.rint(V / Vs_n * DUTY_MAX), -DUTY_MAX, DUTY_MAX)))
                    if record:
                        tr[0, k, i] = x0[l]
                        tr[1, k, i] = x1[l]
                        tr[2, k, i] = x2[l]
                        tr[3, k, i] = x3[l]
                        tr[4, k, i] = u
                        tr[5, k, i] = _rhs(x1[l], x2[l], x3[l], duty[l], u, motor, fpa[i], Vs[i], R[i], kt[i],
                                           gear[i], rw[i], Mm[i], J[i], mL[i], b[i], g[i], accel, al)[2]
                        tr[6, k, i] = duty[l]
                        tr[7, k, i] = W[l, nz]
                        tr[8, k, i] = W[l, nz + 1]
                    for r in range(nz):
                        W[l, r] = out[l, r + 2] + Bu[r, gi] * u
                if k == n_ticks:
                    break
                # --- plant: RK4 sub-steps with the duty (or force) held, stage by stage over the lanes
                for _ in range(sub):
                    for l in range(nl):
                        i = i0 + l
                        xdd, phidd, F = _rhs(x1[l], x2[l], x3[l], duty[l], us[l], motor, fpa[i], Vs[i], R[i], kt[i],
                                             gear[i], rw[i], Mm[i], J[i], mL[i], b[i], g[i], accel, al)
                        k1[l, 0], k1[l, 1], k1[l, 2], k1[l, 3] = x1[l], xdd, x3[l], phidd
                        Fk[l] = F
                    for l in range(nl):
                        i = i0 + l
                        y1, y2, y3 = x1[l] + hh * k1[l, 1], x2[l] + hh * k1[l, 2], x3[l] + hh * k1[l, 3]
                        xdd, phidd, F = _rhs(y1, y2, y3, duty[l], us[l], motor, fpa[i], Vs[i], R[i], kt[i],
                                             gear[i], rw[i], Mm[i], J[i], mL[i], b[i], g[i], accel, al)
                        k2[l, 0], k2[l, 1], k2[l, 2], k2[l, 3] = y1, xdd, y3, phidd
                    for l in range(nl):
                        i = i0 + l
                        y1, y2, y3 = x1[l] + hh * k2[l, 1], x2[l] + hh * k2[l, 2], x3[l] + hh * k2[l, 3]
                        xdd, phidd, F = _rhs(y1, y2, y3, duty[l], us[l], motor, fpa[i], Vs[i], R[i], kt[i],
                                             gear[i], rw[i], Mm[i], J[i], mL[i], b[i], g[i], accel, al)
                        k3[l, 0], k3[l, 1], k3[l, 2], k3[l, 3] = y1, xdd, y3, phidd
                    for l in range(nl):
                        i = i0 + l
                        y1, y2, y3 = x1[l] + h * k3[l, 1], x2[l] + h * k3[l, 2], x3[l] + h * k3[l, 3]
                        xdd, phidd, F = _rhs(y1, y2, y3, duty[l], us[l], motor, fpa[i], Vs[i], R[i], kt[i],
                                             gear[i], rw[i], Mm[i], J[i], mL[i], b[i], g[i], accel, al)
                        k4[l, 0], k4[l, 1], k4[l, 2], k4[l, 3] = y1, xdd, y3, phidd
                    for l in range(nl):
                        F = Fk[l]
                        am[l] = _max(am[l], abs(k1[l, 1]))
                        fm[l] = _max(fm[l], abs(F))
                        if sample >= w0:
                            psq[l] = psq[l] + x2[l] * x2[l]
                            fsq[l] = fsq[l] + F * F
                        x0[l] = x0[l] + h6 * (k1[l, 0] + 2 * k2[l, 0] + 2 * k3[l, 0] + k4[l, 0])
                        x1[l] = x1[l] + h6 * (k1[l, 1] + 2 * k2[l, 1] + 2 * k3[l, 1] + k4[l, 1])
                        x2[l] = x2[l] + h6 * (k1[l, 2] + 2 * k2[l, 2] + 2 * k3[l, 2] + k4[l, 2])
                        x3[l] = x3[l] + h6 * (k1[l, 3] + 2 * k2[l, 3] + 2 * k3[l, 3] + k4[l, 3])
                        ap = abs(x2[l])
                        pm[l] = _max(pm[l], ap)
                        xm[l] = _max(xm[l], abs(x0[l]))
                        if ap > band:
                            lo[l] = sample + 1
                    sample += 1
            for l in range(nl):
                i = i0 + l
                phi_max[i] = pm[l]
                x_max[i] = xm[l]
                xdd_max[i] = am[l]
                f_max[i] = fm[l]
                last_out[i] = lo[l]
                phi_sq[i] = psq[l]
                f_sq[i] = fsq[l]

else:  # pragma: no cover

    def run_chunk(*args, **kwargs):  # noqa: ANN002, ANN003, ANN201
        raise RuntimeError("numba is not installed: use engine='numpy'")
