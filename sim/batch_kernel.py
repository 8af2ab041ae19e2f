"""The compiled inner loop of :func:`sim.batch.simulate_batch` (``engine="numba"``).

The runs of a chunk go in groups of :data:`LANES` (16), spread over the cores
(``numba.prange``), each group advanced tick by tick with all its runs side by side.  The
arithmetic is the numpy reference's (:func:`sim.batch._loop_numpy`), operation for operation,
so that a run's metrics and traces are **bit-identical** to the reference's
(``tests/test_batch_kernel.py`` checks ``array_equal`` on hundreds of runs with delay,
quantisation, noise, saturation and the acceleration clip):

* the same expression trees in the same order (IEEE arithmetic is not associative); compiled
  without ``fastmath`` so LLVM neither reassociates nor contracts ``a*b + c`` into an FMA.
  Only common subexpressions are computed once (the same tree gives the same value): the
  motor voltage of the tick's duty, ``(M + m) * J`` and ``mL * g`` of the run, the terms of
  the acceleration clip that do not involve the force;
* the controller's matrix product as a sequential sum over the columns, as the reference
  writes it (no BLAS, no einsum);
* ``sin``/``cos`` from the C library: numba lowers ``math.sin``/``math.cos`` to the libm
  calls, and LLVM turns the sine and cosine of one angle into one glibc ``sincos`` call
  (one argument reduction for both; glibc's ``sincos`` shares ``sin``'s and ``cos``'s code and
  gives their values).  numpy's ``np.sin``/``np.cos`` call the same libm functions where
  numpy has no vectorised float64 version of its own (x86-64 without AVX-512; with AVX-512
  numpy may use its own SIMD sin/cos and the engines can then differ in the last bit):
  :func:`kernel_trig_is_numpys` checks the kernel's compiled trig against numpy's on the
  machine, :func:`numpy_trig_is_libm` numpy's against Python's ``math``;
* numpy's NaN-propagating ``maximum``/``clip`` and round-half-even ``rint``;
* the noise of run ``i`` drawn from its own generator ``default_rng(noise_seed[i])``, value
  for value what :class:`sim.batch._NoiseStream` draws: in the kernel, through the C
  functions numpy's ``Generator.random``/``standard_normal`` call once per value
  (:func:`draw_functions`), or -- where numpy does not export them -- drawn beforehand into
  an ``(N, T, 2)`` array.

Speed (``make bench``, :mod:`host.bench.batch`): the lanes of a group sit side by side in
one ``(rows, LANES)`` array, so that LLVM's loop vectoriser turns each lane loop into AVX
instructions (four runs per instruction, the divisions included), while the independent
``sincos`` calls of 16 runs keep the core busy; about half of the time is ``sincos`` itself
(4 evaluations per RK4 step per run).  The noise is drawn in the kernel (no array in memory,
drawn in parallel).  The compiled code is cached on disk (``cache=True``: ``sim/__pycache__``;
no address of the process is compiled in), so only the first use on a machine pays the
compilation (~40 s).
"""

from __future__ import annotations

import ctypes
import math
from functools import lru_cache

import numpy as np

from .plantsim import PlantSim

try:  # numba is optional: without it simulate_batch uses the numpy reference
    import numba
    from llvmlite import ir
    from numba import njit, prange, types
    from numba.extending import intrinsic

    AVAILABLE = True
except ImportError:  # pragma: no cover - exercised only without numba
    numba = None
    AVAILABLE = False

__all__ = ["AVAILABLE", "run_chunk", "numpy_trig_is_libm", "kernel_trig_is_numpys", "threads",
           "draw_functions", "bitgen_address", "NOISE_NONE", "NOISE_ARRAY", "NOISE_DRAW"]

ENC_MODULUS = 1 << 16
LANES = 16  # runs advanced side by side in the kernel
DUTY_MAX = 32767.0

# rows of a lane group's float workspace (run_chunk): state, per-run constants, the tick's
# held inputs, the RK4 stage input and its derivatives (xdot, xddot, phidot, phiddot, force)
(_X0, _X1, _X2, _X3, _FPA, _VS, _R, _KT, _GEAR, _RW, _MM, _J, _ML, _B, _MMJ, _MLG,
 _US, _DUTY, _VM, _Y1, _Y2, _Y3, _SN, _CS, _F, _PM, _XM, _AM, _FM, _PSQ, _FSQ, _UMAX) = range(32)
_NX, _NPHI = 32, 33  # the noise of the current hold period
_K1, _K2, _K3, _K4 = 34, 39, 44, 49
# plant realism (sim.batch._Realism): the gear play's state and half width, friction, the
# sliding direction and its force, stuck (1.0) or not, the gear's contact, the motor's
# no-load speed, the pot's nonlinearity amplitude, the bridge's deadband and minimum duty,
# the lane's flags (play, friction), the cart position at the sub-step's start, the share of the
# sub-step after a contact located in it and the cart speed at the sub-step's start
(_DL, _HP, _FC, _FS, _DIR, _FF, _STK, _ENG, _V0, _AMP, _DB, _DMIN, _PLAY, _FRIC, _XOLD, _SHR,
 _VIN) = range(54, 71)
_NROWS = 71

NOISE_NONE, NOISE_ARRAY, NOISE_DRAW = 0, 1, 2
"""Noise sources of :func:`run_chunk`: none, an ``(N, T, 2)`` array drawn beforehand, or drawn
in the kernel from each run's generator (:func:`draw_functions`)."""

# PyCapsule_GetPointer with its own prototype (not ctypes.pythonapi's shared function object,
# whose argtypes other code may rely on)
_capsule_pointer = ctypes.PYFUNCTYPE(ctypes.c_void_p, ctypes.py_object, ctypes.c_char_p)(
    ("PyCapsule_GetPointer", ctypes.pythonapi))


def bitgen_address(gen: np.random.Generator) -> int:
    """Address of the C ``bitgen_t`` of ``gen``'s bit generator (its ``"BitGenerator"`` capsule).

    Valid while ``gen`` lives; whoever draws through it must be the generator's only user
    (numpy's lock is not taken).
    """
    return int(_capsule_pointer(gen.bit_generator.capsule, b"BitGenerator"))


@lru_cache(maxsize=None)
def draw_functions() -> dict[str, int] | None:
    """Addresses of numpy's C ``random_standard_uniform`` and ``random_standard_normal``.

    The functions ``Generator.random`` and ``Generator.standard_normal`` call once per value
    (``double f(bitgen_t *)``, exported by ``numpy.random._generator``), so that the kernel
    draws each run's noise from the run's own generator, value for value what
    :class:`sim.batch._NoiseStream` draws, without an ``(N, T, 2)`` array in memory.  Checked
    against the generator methods on first use.

    Returns
    -------
    dict or None
        ``{"uniform": address, "white": address}``; None where numpy does not export them
        (or they draw differently): the caller then draws the noise beforehand.
    """
    try:
        from numpy.random import _generator

        lib = ctypes.CDLL(_generator.__file__)
        fns = {"uniform": lib.random_standard_uniform, "white": lib.random_standard_normal}
    except (ImportError, OSError, AttributeError):  # pragma: no cover - other numpy builds
        return None
    out = {}
    for kind, fn in fns.items():
        addr = ctypes.cast(fn, ctypes.c_void_p).value
        call = ctypes.CFUNCTYPE(ctypes.c_double, ctypes.c_void_p)(addr)
        ref_gen, gen = np.random.default_rng(20260), np.random.default_rng(20260)
        ref = np.empty((64, 2))
        (ref_gen.random if kind == "uniform" else ref_gen.standard_normal)(out=ref)
        state = bitgen_address(gen)
        got = np.array([call(state) for _ in range(ref.size)])
        if not np.array_equal(ref.ravel(), got):  # pragma: no cover - other numpy builds
            return None
        out[kind] = int(addr)
    return out


def numpy_trig_is_libm(n: int = 4096, seed: int = 7) -> bool:
    """True if ``np.sin``/``np.cos`` give exactly ``math.sin``/``math.cos`` (libm) on this machine.

    The condition under which the compiled kernel is bit-identical to the numpy reference.
    """
    rng = np.random.default_rng(seed)
    x = np.concatenate([rng.standard_normal(n) * s for s in (0.01, 0.3, 2.0, 50.0)])
    s, c = np.sin(x), np.cos(x)
    return all(s[i] == math.sin(v) and c[i] == math.cos(v) for i, v in enumerate(x.tolist()))


def kernel_trig_is_numpys(n: int = 200_000, seed: int = 11) -> bool:
    """True if the kernel's compiled ``sin``/``cos`` give exactly ``np.sin``/``np.cos`` here.

    The kernel's trig as compiled (the sine and cosine of one angle, which LLVM turns into
    one ``sincos`` call) on ``n`` values at each of several scales (tiny to ``1e9`` rad,
    both signs), compared bit for bit with numpy's -- the condition under which the kernel
    is bit-identical to the numpy reference.  False without numba.
    """
    if not AVAILABLE:
        return False
    rng = np.random.default_rng(seed)
    scales = (1e-9, 1e-3, 0.05, 0.3, 0.9, 1.6, 3.2, 10.0, 1e3, 1e9)
    x = np.concatenate([rng.standard_normal(n) * sc for sc in scales])
    s, c = np.empty_like(x), np.empty_like(x)
    _kernel_trig(x, s, c)
    return bool(np.array_equal(s.view(np.int64), np.sin(x).view(np.int64))
                and np.array_equal(c.view(np.int64), np.cos(x).view(np.int64)))


def threads() -> int:
    """Threads the kernel runs on (numba's, ``NUMBA_NUM_THREADS``); 1 without numba."""
    return int(numba.get_num_threads()) if AVAILABLE else 1


if AVAILABLE:

    @intrinsic
    def _draw(typingctx, fn, state):  # noqa: ANN001, ANN202
        # double fn(bitgen_t *state), both given as integer addresses at run time (so that
        # the cached machine code holds no address of this process)
        if not (isinstance(fn, types.Integer) and isinstance(state, types.Integer)):
            return None
        sig = types.float64(fn, state)

        def codegen(context, builder, signature, args):  # noqa: ANN001, ANN202
            ptr = ir.IntType(8).as_pointer()
            fnty = ir.FunctionType(ir.DoubleType(), [ptr])
            f = builder.inttoptr(args[0], fnty.as_pointer())
            return builder.call(f, [builder.inttoptr(args[1], ptr)])

        return sig, codegen

    @njit(cache=True)
    def _kernel_trig(x, s, c):  # noqa: ANN001, ANN202
        # sine and cosine of one angle, as _stage computes them (LLVM fuses them into sincos)
        for i in range(x.size):
            v = x[i]
            s[i] = math.sin(v)
            c[i] = math.cos(v)

    @njit(cache=True, inline="always")
    def _max(a: float, b: float) -> float:
        # numpy's maximum: the first argument if it is NaN or >= the second, else the second
        return a if (a >= b or a != a) else b

    @njit(cache=True, inline="always")
    def _clip(a: float, lo: float, hi: float) -> float:
        # numpy's clip: min(max(a, lo), hi) with NaN kept
        if a != a:
            return a
        v = a if a > lo else lo
        return v if (v < hi or v != v) else hi

    @njit(cache=True, inline="always")
    def _force(S, l, x1, motor):  # noqa: ANN001, ANN202
        # the true motor's force at cart speed x1 (sim.motor.force_from_duty with the tick's
        # voltage), or the held force with drive="force"
        if motor:
            w = S[_GEAR, l] * x1 / S[_RW, l]
            return S[_FPA, l] * ((S[_VM, l] - S[_KT, l] * w) / S[_R, l])
        return S[_US, l]

    @njit(cache=True, inline="always")
    def _accel_clip(F, x1, x3, s, c, S, l, al):  # noqa: ANN001, ANN202
        # the reference's acceleration clip: xddot(F) is affine in F; a0 = xddot(0),
        # a1 = xddot(1) - a0, F clipped to keep |xddot| <= al (sim.plant.dynamics term for
        # term: F - b*xd - mL*phid*phid*s, mL*g*s, ...; the parts without F computed once)
        t1 = S[_B, l] * x1
        t2 = S[_ML, l] * x3 * x3 * s
        rhs2 = S[_MLG, l] * s
        mLc = S[_ML, l] * c
        det = S[_MMJ, l] - mLc * mLc
        J = S[_J, l]
        a0 = (J * (0.0 - t1 - t2) + mLc * rhs2) / det
        a1 = (J * (1.0 - t1 - t2) + mLc * rhs2) / det - a0
        return _clip(F, (-al - a0) / a1, (al - a0) / a1)

    @njit(cache=True, inline="always")
    def _force1(S, l, motor, accel, al):  # noqa: ANN001, ANN202
        # the force the first RK4 stage applies at the current state (the "force" trace)
        x1, x2, x3 = S[_X1, l], S[_X2, l], S[_X3, l]
        F = _force(S, l, x1, motor)
        if accel:
            F = _accel_clip(F, x1, x3, math.sin(x2), math.cos(x2), S, l, al)
        return F

    @njit(cache=True, inline="always")
    def _stage(S, kr, motor, accel, al):  # noqa: ANN001, ANN202
        # one RK4 stage for every lane: the reference's rhs() at (Y1, Y2, Y3) -> rows
        # kr .. kr+4 = xdot, xddot, phidot, phiddot, force.  Split into lane loops without
        # branches inside (the flags are tested outside), so that each packs into SIMD;
        # sin and cos of the same angle become one libm sincos call (LLVM fuses them)
        for l in range(LANES):
            y2 = S[_Y2, l]
            S[_SN, l] = math.sin(y2)
            S[_CS, l] = math.cos(y2)
        for l in range(LANES):
            S[_F, l] = _force(S, l, S[_Y1, l], motor)
        if accel:
            for l in range(LANES):
                S[_F, l] = _accel_clip(S[_F, l], S[_Y1, l], S[_Y3, l], S[_SN, l], S[_CS, l], S, l, al)
        for l in range(LANES):
            x1, x3, s, c, F = S[_Y1, l], S[_Y3, l], S[_SN, l], S[_CS, l], S[_F, l]
            rhs1 = F - S[_B, l] * x1 - S[_ML, l] * x3 * x3 * s
            rhs2 = S[_MLG, l] * s
            mLc = S[_ML, l] * c
            det = S[_MMJ, l] - mLc * mLc
            S[kr, l] = x1
            S[kr + 1, l] = (S[_J, l] * rhs1 + mLc * rhs2) / det
            S[kr + 2, l] = x3
            S[kr + 3, l] = (mLc * rhs1 + S[_MM, l] * rhs2) / det
            S[kr + 4, l] = F

    @njit(cache=True, inline="always")
    def _gate(F, e):  # noqa: ANN001, ANN202
        # the motor force the gear passes (sim.batch._gate): all of it without play (2), only a
        # push into the flank in contact (+1, -1), nothing while free in the play (0)
        if e == 2.0:
            return F
        if e == 1.0:
            return F if F > 0.0 else 0.0
        if e == -1.0:
            return F if F < 0.0 else 0.0
        return 0.0

    # the located events (a contact within the sub-step, a stop the drive reverses at once): the
    # scenario simulator's own functions, compiled -- the reference's arithmetic, operation for operation
    _contact_share = njit(cache=True, inline="always")(PlantSim._contact_share)
    _stop = njit(cache=True, inline="always")(PlantSim._stop)

    @njit(cache=True, inline="always")
    def _engagement(S, l):  # noqa: ANN001, ANN202
        # sim.batch._engagement
        if S[_PLAY, l] > 0.0:
            d, hp = S[_DL, l], S[_HP, l]
            return 1.0 if d >= hp else (-1.0 if d <= -hp else 0.0)
        return 2.0

    @njit(cache=True, inline="always")
    def _force1_real(S, l, motor, accel, al):  # noqa: ANN001, ANN202
        # _force1 through the gear play (the contact of the sub-step, row _ENG)
        x1, x2, x3 = S[_X1, l], S[_X2, l], S[_X3, l]
        F = _force(S, l, x1, motor)
        if motor:
            F = _gate(F, S[_ENG, l])
            if S[_SHR, l] > 0.0:
                F = S[_SHR, l] * F
        if accel:
            F = _accel_clip(F, x1, x3, math.sin(x2), math.cos(x2), S, l, al)
        return F

    @njit(cache=True, inline="always")
    def _stage_real(S, kr, motor, accel, al):  # noqa: ANN001, ANN202
        # _stage with plant realism (sim.batch rhs_real): the motor force through the gear play,
        # Coulomb friction -FF on a sliding cart, and a stuck cart's pendulum on a fixed pivot
        for l in range(LANES):
            y2 = S[_Y2, l]
            S[_SN, l] = math.sin(y2)
            S[_CS, l] = math.cos(y2)
        for l in range(LANES):
            F = _force(S, l, S[_Y1, l], motor)
            if motor:
                F = _gate(F, S[_ENG, l])
                if S[_SHR, l] > 0.0:
                    F = S[_SHR, l] * F
            S[_F, l] = F
        if accel:
            for l in range(LANES):
                S[_F, l] = _accel_clip(S[_F, l], S[_Y1, l], S[_Y3, l], S[_SN, l], S[_CS, l], S, l, al)
        for l in range(LANES):
            x1, x3, s, c, F = S[_Y1, l], S[_Y3, l], S[_SN, l], S[_CS, l], S[_F, l]
            Ft = F - S[_FF, l] if S[_FRIC, l] > 0.0 else F
            rhs1 = Ft - S[_B, l] * x1 - S[_ML, l] * x3 * x3 * s
            rhs2 = S[_MLG, l] * s
            mLc = S[_ML, l] * c
            det = S[_MMJ, l] - mLc * mLc
            S[kr, l] = x1
            S[kr + 2, l] = x3
            S[kr + 4, l] = F
            if S[_STK, l] > 0.0:
                S[kr + 1, l] = 0.0
                S[kr + 3, l] = S[_MLG, l] * s / S[_J, l]
            else:
                S[kr + 1, l] = (S[_J, l] * rhs1 + mLc * rhs2) / det
                S[kr + 3, l] = (mLc * rhs1 + S[_MM, l] * rhs2) / det

    @njit(cache=True, inline="always")
    def _stage_input(S, kr, step):  # noqa: ANN001, ANN202
        # the next RK4 stage's input for every lane: state + step x the derivatives in rows
        # kr+1 .. kr+3 (x itself is not an input of rhs())
        for l in range(LANES):
            S[_Y1, l] = S[_X1, l] + step * S[kr + 1, l]
            S[_Y2, l] = S[_X2, l] + step * S[kr + 2, l]
            S[_Y3, l] = S[_X3, l] + step * S[kr + 3, l]

    @njit(cache=True, parallel=True, nogil=True)
    def run_chunk(  # noqa: PLR0913, PLR0915
        n_ticks, sub, h, w0, band,
        X0, x_ref, delay,
        nmode, noise, bitgens, draw_fn, hold, n_affine, n_off, n_scl, mask_x, mask_phi,
        Mm, J, mL, b, g,
        fpa, Vs, R, kt, gear, rw,
        motor, vmeas, fpa_n, Vs_n, R_n, kt_n, gear_n, rw_n,
        cpm_p, cpr_p, off_p, full_p, cpm_f, cpr_f, off_f,
        G, Bu, u_max, gidx,
        accel, al,
        phi_max, x_max, xdd_max, f_max, last_out, phi_sq, f_sq,
        record, tr,
        real, fc, fs, hp, db, dmin, amp, inl_w,
    ):  # noqa: ANN001
        """Simulate the runs of one chunk (arrays of length ``N`` = the chunk's runs).

        ``G`` (NG, nz+3, nz+2), ``Bu`` (nz, NG), ``u_max`` (NG,): the linear part of each
        controller (``G[c, j]`` the column ``j`` of controller ``c``), ``gidx`` (N,) the
        controller of each run.  Noise (``nmode``): :data:`NOISE_NONE`; :data:`NOISE_ARRAY`,
        ``noise`` (N, T, 2); :data:`NOISE_DRAW`, run ``i`` draws ``[x, phi]`` every ``hold``
        ticks with ``draw_fn(bitgens[i])`` (addresses, :func:`draw_functions`,
        :func:`bitgen_address`) and scales it as :class:`sim.batch._NoiseStream` does
        (``n_off + n_scl * u`` if ``n_affine`` else ``u * n_scl``, times the channel's mask).
        Outputs: the metric accumulators (N,) and, with ``record``, ``tr`` (9, T, N) = x, xdot,
        phi, phidot, u_sat, force, duty, x_meas, phi_meas.  ``vmeas``: the firmware inverts the
        motor with the run's true supply (measured) instead of ``Vs_n``.  ``real``: plant realism
        (per run: Coulomb ``fc`` and breakaway ``fs`` friction, half the gear play ``hp``, the
        bridge's deadband ``db`` and minimum duty ``dmin``, the pot's nonlinearity ``amp`` in
        counts at ``inl_w`` rad per count), the scheme of ``sim.batch``'s numpy reference.

        The runs go in groups of ``LANES``, advanced together stage by stage: each run is a
        long chain of dependent operations (sin -> det -> division -> next RK4 stage), and
        independent chains side by side keep the core busy.  A group's floats live in one
        ``(rows, LANES)`` array (row = quantity, column = lane) and every lane loop has
        ``LANES`` iterations (a short last group repeats its last run in the spare lanes, which
        draw no noise and whose results are dropped), so that the loop vectoriser packs four
        lanes' identical operations into one AVX instruction -- each lane's arithmetic is still
        its own, in the reference's order.
        """
        N = X0.shape[0]
        nz = Bu.shape[0]
        nr = nz + 2
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
            S = np.zeros((_NROWS, K))  # the group's floats, one column per lane
            run = np.empty(K, np.int64)  # the run of each lane
            ring_e = np.empty((K, Lmax), np.int64)
            ring_a = np.empty((K, Lmax), np.int64)
            pos = np.zeros(K, np.int64)  # next slot of the delay line (the oldest reading)
            enc_last = np.empty(K, np.int64)
            enc_total = np.empty(K, np.int64)
            lo = np.empty(K, np.int64)
            GL = np.empty((nw, nr, K))  # each lane's controller: GL[j, r, l] = G[gidx, j, r]
            BuL = np.empty((nz, K))
            W = np.zeros((nw, K))  # controller state and inputs [z; v] of each lane
            out = np.empty((nr, K))  # [u; xdot_est; z']
            for l in range(K):
                i = i0 + min(l, nl - 1)
                run[l] = i
                gi = gidx[i]
                for j in range(nw):
                    for r in range(nr):
                        GL[j, r, l] = G[gi, j, r]
                for r in range(nz):
                    BuL[r, l] = Bu[r, gi]
                S[_UMAX, l] = u_max[gi]
                S[_X0, l], S[_X1, l], S[_X2, l], S[_X3, l] = X0[i, 0], X0[i, 1], X0[i, 2], X0[i, 3]
                S[_FPA, l], S[_VS, l], S[_R, l], S[_KT, l] = fpa[i], Vs[i], R[i], kt[i]
                S[_GEAR, l], S[_RW, l], S[_MM, l], S[_J, l] = gear[i], rw[i], Mm[i], J[i]
                S[_ML, l], S[_B, l] = mL[i], b[i]
                # products of per-run constants the reference evaluates first in its
                # expressions ((M + m) * J - ..., mL * g * s): the same values, once
                S[_MMJ, l] = Mm[i] * J[i]
                S[_MLG, l] = mL[i] * g[i]
                S[_FC, l], S[_FS, l], S[_HP, l] = fc[i], fs[i], hp[i]
                S[_DB, l], S[_DMIN, l], S[_AMP, l] = db[i], dmin[i], amp[i]
                S[_PLAY, l] = 1.0 if (real and motor and hp[i] > 0.0) else 0.0
                S[_FRIC, l] = 1.0 if (real and fs[i] > 0.0) else 0.0
                S[_DL, l] = 0.0
                S[_DIR, l] = 1.0 if S[_X1, l] >= 0.0 else -1.0
                S[_STK, l] = 1.0 if (S[_FRIC, l] > 0.0 and S[_X1, l] == 0.0) else 0.0
                S[_ENG, l] = 2.0
                e0 = np.int64(np.rint((S[_X0, l] + 0.0) * cpm_p)) % ENC_MODULUS
                lin = off_p + (S[_X2, l] + 0.0) * cpr_p
                if real and S[_AMP, l] != 0.0:
                    lin = lin + S[_AMP, l] * math.sin(inl_w * lin)
                a0 = np.int64(_clip(np.rint(lin), 0.0, full_p))
                for q in range(delay[i] + 1):
                    ring_e[l, q] = e0
                    ring_a[l, q] = a0
                enc_last[l] = e0
                dd = e0 % ENC_MODULUS
                enc_total[l] = dd - ENC_MODULUS if dd >= ENC_MODULUS // 2 else dd
                W[nz + 2, l] = x_ref[i]
                S[_PM, l] = abs(S[_X2, l])
                S[_XM, l] = abs(S[_X0, l])
                lo[l] = 0 if S[_PM, l] > band else -1
            sample = 0
            for k in range(n_ticks + 1):
                if nmode == NOISE_DRAW and k % hold == 0:
                    # a new noise sample per hold period, [x, phi] in the generator's order
                    # (sim.batch._NoiseStream); spare lanes draw nothing (they repeat a run)
                    for l in range(nl):
                        state = bitgens[run[l]]
                        ux = _draw(draw_fn, state)
                        up = _draw(draw_fn, state)
                        if n_affine:  # uniform: lo + (hi - lo) * u
                            S[_NX, l] = (n_off + n_scl * ux) * mask_x
                            S[_NPHI, l] = (n_off + n_scl * up) * mask_phi
                        else:  # white: u * std
                            S[_NX, l] = (ux * n_scl) * mask_x
                            S[_NPHI, l] = (up * n_scl) * mask_phi
                # --- sensors: this tick's reading enters the delay line, the delayed one leaves
                for l in range(K):
                    i = run[l]
                    if nmode == NOISE_ARRAY:
                        nx = noise[i, k, 0]
                        nphi = noise[i, k, 1]
                    else:
                        nx = S[_NX, l]
                        nphi = S[_NPHI, l]
                    p = pos[l]
                    # the motor encoder reads the motor side of the gear play
                    xe = S[_X0, l] + S[_DL, l] if S[_PLAY, l] > 0.0 else S[_X0, l]
                    ring_e[l, p] = np.int64(np.rint((xe + nx) * cpm_p)) % ENC_MODULUS
                    lin = off_p + (S[_X2, l] + nphi) * cpr_p
                    if real and S[_AMP, l] != 0.0:  # the pot's nonlinearity (sim.sensors.phi_to_adc)
                        lin = lin + S[_AMP, l] * math.sin(inl_w * lin)
                    ring_a[l, p] = np.int64(_clip(np.rint(lin), 0.0, full_p))
                    p = p + 1 if p < delay[i] else 0  # (k - delay) % (delay + 1) == (k + 1) % (delay + 1)
                    pos[l] = p
                    seen_e = ring_e[l, p]
                    seen_a = ring_a[l, p]
                    dd = (seen_e - enc_last[l]) % ENC_MODULUS
                    enc_total[l] = enc_total[l] + (dd - ENC_MODULUS if dd >= ENC_MODULUS // 2 else dd)
                    enc_last[l] = seen_e
                    W[nz, l] = enc_total[l] / cpm_f
                    W[nz + 1, l] = (float(seen_a) - off_f) / cpr_f
                # --- controller: rows [u; xdot_est; z'] = G [z; v], each row summed over the
                # columns in order (the reference's sum), all lanes at once (SIMD), four
                # columns per pass so that the partial sums stay in registers
                for r in range(nr):
                    for l in range(K):
                        out[r, l] = GL[0, r, l] * W[0, l]
                    j = 1
                    while j + 4 <= nw:
                        for l in range(K):
                            out[r, l] = (((out[r, l] + GL[j, r, l] * W[j, l]) + GL[j + 1, r, l] * W[j + 1, l])
                                         + GL[j + 2, r, l] * W[j + 2, l]) + GL[j + 3, r, l] * W[j + 3, l]
                        j += 4
                    if nw - j == 3:
                        for l in range(K):
                            out[r, l] = ((out[r, l] + GL[j, r, l] * W[j, l]) + GL[j + 1, r, l] * W[j + 1, l]
                                         ) + GL[j + 2, r, l] * W[j + 2, l]
                    elif nw - j == 2:
                        for l in range(K):
                            out[r, l] = (out[r, l] + GL[j, r, l] * W[j, l]) + GL[j + 1, r, l] * W[j + 1, l]
                    elif nw - j == 1:
                        for l in range(K):
                            out[r, l] = out[r, l] + GL[j, r, l] * W[j, l]
                for l in range(K):
                    S[_US, l] = _clip(out[0, l], -S[_UMAX, l], S[_UMAX, l])
                if motor:
                    for l in range(K):
                        u = S[_US, l]
                        ii = u / fpa_n
                        w = gear_n * out[1, l] / rw_n
                        V = ii * R_n + kt_n * w
                        # the firmware's supply: nominal, or measured (the lane's true supply)
                        vf = S[_VS, l] if vmeas else Vs_n
                        S[_DUTY, l] = float(np.int64(_clip(np.rint(V / vf * DUTY_MAX), -DUTY_MAX, DUTY_MAX)))
                        # the true motor's voltage, held over the tick (sim.motor.current_from_duty)
                        if real:  # through the bridge's minimum duty and deadband (sim.motor.bridge_fraction)
                            u = _clip(S[_DUTY, l], -DUTY_MAX, DUTY_MAX) / DUTY_MAX
                            a = abs(u)
                            if a < S[_DMIN, l]:
                                a = 0.0
                            a = a - S[_DB, l]
                            a = a if a > 0.0 else 0.0
                            S[_VM, l] = math.copysign(a, u) * S[_VS, l]
                            # the motor's no-load speed (m/s of cart travel)
                            S[_V0, l] = S[_VM, l] * S[_RW, l] / (S[_KT, l] * S[_GEAR, l])
                        else:
                            S[_VM, l] = _clip(S[_DUTY, l], -DUTY_MAX, DUTY_MAX) / DUTY_MAX * S[_VS, l]
                if record:
                    for l in range(nl):
                        i = run[l]
                        tr[0, k, i] = S[_X0, l]
                        tr[1, k, i] = S[_X1, l]
                        tr[2, k, i] = S[_X2, l]
                        tr[3, k, i] = S[_X3, l]
                        tr[4, k, i] = S[_US, l]
                        if real:
                            S[_ENG, l] = _engagement(S, l)
                            S[_SHR, l] = 0.0
                            tr[5, k, i] = _force1_real(S, l, motor, accel, al)
                        else:
                            tr[5, k, i] = _force1(S, l, motor, accel, al)
                        tr[6, k, i] = S[_DUTY, l]
                        tr[7, k, i] = W[nz, l]
                        tr[8, k, i] = W[nz + 1, l]
                for r in range(nz):
                    for l in range(K):
                        W[r, l] = out[r + 2, l] + BuL[r, l] * S[_US, l]
                if k == n_ticks:
                    break
                # --- plant: RK4 sub-steps with the duty (or force) held, stage by stage over the lanes
                if real:
                    for _ in range(sub):
                        # the gear's contact, sticking or sliding, the sliding direction: decided
                        # at the sub-step's start and held over it (sim.batch's numpy reference)
                        for l in range(K):
                            S[_ENG, l] = _engagement(S, l)
                            S[_SHR, l] = 0.0
                            # a contact within the sub-step, located in it (sim.batch._contact_share)
                            rel = S[_V0, l] - S[_X1, l]
                            shr = _contact_share(S[_ENG, l], S[_DL, l], S[_HP, l], rel, h)
                            if shr > 0.0:
                                S[_SHR, l] = shr
                                S[_ENG, l] = 1.0 if rel > 0.0 else -1.0
                            F0 = _force1_real(S, l, motor, accel, al)
                            if S[_FRIC, l] > 0.0:
                                if S[_STK, l] > 0.0:
                                    x2, x3 = S[_X2, l], S[_X3, l]
                                    sn = math.sin(x2)
                                    cs = math.cos(x2)
                                    fext = (F0 + (S[_ML, l] * cs) * ((S[_MLG, l] * sn) / S[_J, l])) \
                                        - S[_ML, l] * x3 * x3 * sn
                                    if abs(fext) > S[_FS, l]:
                                        S[_STK, l] = 0.0
                                        S[_DIR, l] = 1.0 if fext > 0.0 else -1.0
                                elif S[_X1, l] != 0.0:
                                    S[_DIR, l] = 1.0 if S[_X1, l] > 0.0 else -1.0
                            S[_FF, l] = S[_FC, l] * S[_DIR, l]
                            S[_Y1, l], S[_Y2, l], S[_Y3, l] = S[_X1, l], S[_X2, l], S[_X3, l]
                            S[_XOLD, l] = S[_X0, l]
                            S[_VIN, l] = S[_X1, l]
                        _stage_real(S, _K1, motor, accel, al)
                        _stage_input(S, _K1, hh)
                        _stage_real(S, _K2, motor, accel, al)
                        _stage_input(S, _K2, hh)
                        _stage_real(S, _K3, motor, accel, al)
                        _stage_input(S, _K3, h)
                        _stage_real(S, _K4, motor, accel, al)
                        for l in range(K):
                            F = S[_K1 + 4, l]
                            S[_AM, l] = _max(S[_AM, l], abs(S[_K1 + 1, l]))
                            S[_FM, l] = _max(S[_FM, l], abs(F))
                        if sample >= w0:
                            for l in range(K):
                                F = S[_K1 + 4, l]
                                S[_PSQ, l] = S[_PSQ, l] + S[_X2, l] * S[_X2, l]
                                S[_FSQ, l] = S[_FSQ, l] + F * F
                        for c in range(4):
                            for l in range(K):
                                S[_X0 + c, l] = S[_X0 + c, l] + h6 * (
                                    S[_K1 + c, l] + 2 * S[_K2 + c, l] + 2 * S[_K3 + c, l] + S[_K4 + c, l])
                        for l in range(K):
                            if S[_FRIC, l] > 0.0 and S[_STK, l] == 0.0 and S[_X1, l] * S[_DIR, l] <= 0.0:
                                # stopped sliding: held by static friction, unless the force at rest
                                # breaks it loose the other way at once (sim.batch's reference)
                                Fr = _force(S, l, 0.0, motor)
                                if motor:
                                    Fr = _gate(Fr, S[_ENG, l])
                                x2, x3 = S[_X2, l], S[_X3, l]
                                sn = math.sin(x2)
                                cs = math.cos(x2)
                                fr = (Fr + (S[_ML, l] * cs) * ((S[_MLG, l] * sn) / S[_J, l])) \
                                    - S[_ML, l] * x3 * x3 * sn
                                v, dr, stk = _stop(S[_VIN, l], S[_X1, l], S[_DIR, l], fr, S[_FC, l], S[_FS, l], h,
                                                   S[_MM, l])
                                S[_X1, l], S[_DIR, l] = v, dr
                                if stk:
                                    S[_STK, l] = 1.0
                            if S[_PLAY, l] > 0.0:
                                dl = (S[_DL, l] + h * S[_V0, l]) - (S[_X0, l] - S[_XOLD, l])
                                hpl = S[_HP, l]
                                S[_DL, l] = hpl if dl > hpl else (-hpl if dl < -hpl else dl)
                        sample += 1
                        for l in range(K):
                            ap = abs(S[_X2, l])
                            S[_PM, l] = _max(S[_PM, l], ap)
                            S[_XM, l] = _max(S[_XM, l], abs(S[_X0, l]))
                            if ap > band:
                                lo[l] = sample
                    continue
                for _ in range(sub):
                    for l in range(K):
                        S[_Y1, l], S[_Y2, l], S[_Y3, l] = S[_X1, l], S[_X2, l], S[_X3, l]
                    _stage(S, _K1, motor, accel, al)
                    _stage_input(S, _K1, hh)
                    _stage(S, _K2, motor, accel, al)
                    _stage_input(S, _K2, hh)
                    _stage(S, _K3, motor, accel, al)
                    _stage_input(S, _K3, h)
                    _stage(S, _K4, motor, accel, al)
                    for l in range(K):
                        F = S[_K1 + 4, l]  # the force of the first stage (at the sub-step's start)
                        S[_AM, l] = _max(S[_AM, l], abs(S[_K1 + 1, l]))
                        S[_FM, l] = _max(S[_FM, l], abs(F))
                    if sample >= w0:
                        for l in range(K):
                            F = S[_K1 + 4, l]
                            S[_PSQ, l] = S[_PSQ, l] + S[_X2, l] * S[_X2, l]
                            S[_FSQ, l] = S[_FSQ, l] + F * F
                    for c in range(4):
                        for l in range(K):
                            S[_X0 + c, l] = S[_X0 + c, l] + h6 * (
                                S[_K1 + c, l] + 2 * S[_K2 + c, l] + 2 * S[_K3 + c, l] + S[_K4 + c, l])
                    sample += 1
                    for l in range(K):
                        ap = abs(S[_X2, l])
                        S[_PM, l] = _max(S[_PM, l], ap)
                        S[_XM, l] = _max(S[_XM, l], abs(S[_X0, l]))
                        if ap > band:
                            lo[l] = sample
            for l in range(nl):
                i = i0 + l
                phi_max[i] = S[_PM, l]
                x_max[i] = S[_XM, l]
                xdd_max[i] = S[_AM, l]
                f_max[i] = S[_FM, l]
                last_out[i] = lo[l]
                phi_sq[i] = S[_PSQ, l]
                f_sq[i] = S[_FSQ, l]

else:  # pragma: no cover

    def run_chunk(*args, **kwargs):  # noqa: ANN002, ANN003, ANN201
        raise RuntimeError("numba is not installed: use engine='numpy'")
