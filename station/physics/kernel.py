"""The plant's inner loop, compiled: one SYNC period of drive, motor, chain and sensor front end.

A characterization is up to 100 s of motion at 32 integration steps per
millisecond: over 3 million steps. As scalar Python on ``math`` a belt unit's
88 s took 19 s to simulate, most of what a diagnosis benchmark or a test
suite spent; numba compiles this one function (caching the machine code
beside the module) and the same recording takes 2.5 s, the rest now being
the per-SYNC work of the drive and sensor in Python. The arithmetic is the
loop's as it was, in the same order: the counts came out bit for bit the
same on the ten recordings compared. Nothing else in the station needs numba.

The arguments are flat arrays rather than dozens of scalars: a compiled
call checks the type of every argument, and a SYNC period is short enough
that this check would otherwise cost as much as the integration.
Indices into them are named below; ``Plant`` fills them.

The loop keeps the GIL. A SYNC period is about 10 µs of work: released, the
simulated device's thread would have to win the GIL back after every period,
and behind a busy station thread that waits up to the interpreter's 5 ms
switch interval, which would stall the bench's devices. (A loaded CI run with
the GIL released saw a simulated Modbus drive's keep-alive go unanswered for
5 s; this is the likeliest cause, not a proven one.)
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit
from numpy.typing import NDArray

TABLE_SIZE = 8192
"""Points per period of the harmonic tables (each has one more, the wrap point); linear
interpolation then errs by less than (j·2π/8192)²/8 ≈ 2e-5 of an order-j harmonic's
amplitude (j ≤ 8)."""

# Constants of a unit (``Plant._constants``).
H, NR, KT, REL = 0, 1, 2, 3
LA0, LA1, LA2, LB0, LB1, LB2 = 4, 5, 6, 7, 8, 9
CV0, CP0, CN0, IW0, CVL, CPL, CNL, IWL = 10, 11, 12, 13, 14, 15, 16, 17
J0, J1, JL, K1, C1, N1, K2, C2, N2 = 18, 19, 20, 21, 22, 23, 24, 25, 26
R_OVER_H, INV_ISAT2, ECC, ECC_PHASE, UNB, UNB_PHASE = 27, 28, 29, 30, 31, 32
REL_U, DEAD, INV_KNEE = 33, 34, 35
N_CONSTANTS = 36

# Switches of a unit: which terms it has (0 or 1, NDOF the chain's inertias).
NDOF, HARMONICS, DISTORTION, LAGGED, COULOMB_L, BEYOND, RESHAPING = 0, 1, 2, 3, 4, 5, 6
SATURATING, DETENT_ALONE, ECCENTRIC, DRIFTING, DEAD_TIME, PI_LOOP = 7, 8, 9, 10, 11, 12
N_SWITCHES = 13

# One SYNC period's command.
ENABLED, KX, P0, PV, PA, OFF_A, OFF_B, FA, FB = 0, 1, 2, 3, 4, 5, 6, 7, 8
N_COMMAND = 9

# The state carried from period to period, then what a period leaves to report.
TH0, OM0, TH1, OM1, THL, OML, I_A, I_B, T_A, T_B = 0, 1, 2, 3, 4, 5, 6, 7, 8, 9
ACC0, ACC1, TORQUE = 10, 11, 12
N_STATE = 13


@njit(cache=True)
def _table(table: NDArray[np.float64], angle: float, scale: float, size: int) -> float:
    """A periodic table read at ``angle`` with linear interpolation."""
    q = angle * scale
    kf = math.floor(q)
    fr = q - kf
    k = int(kf) % size
    g = table[k]
    return float(g + (table[k + 1] - g) * fr)


@njit(cache=True)
def integrate(  # noqa: PLR0917 (numba compiles no keyword-only arguments)
    c: NDArray[np.float64], sw: NDArray[np.int64], cmd: NDArray[np.float64],
    state: NDArray[np.float64], harmonics: NDArray[np.float64],
    distortion: NDArray[np.float64], detent: NDArray[np.float64],
    steps: NDArray[np.float64], u_out: NDArray[np.float64],
) -> None:
    """Advance ``state`` by one SYNC period in ``len(steps)`` semi-implicit Euler steps.

    Velocities are updated first from the forces at the current angles, then
    angles from the new velocities (symplectic Euler, so the lightly damped
    modes neither gain nor lose energy numerically). Friction is linearised
    implicitly: the tanh's steep slope near zero speed would otherwise make an
    explicit step unstable. ``u_out`` receives each step's tangential
    acceleration (r·α) when the sensor's clock drifts, for the sample instant.
    """
    size = TABLE_SIZE
    tscale = TABLE_SIZE / (2.0 * math.pi)
    h, nr, kt, rel, rel_u = c[H], c[NR], c[KT], c[REL], c[REL_U]
    ndof = sw[NDOF]
    enabled = cmd[ENABLED] != 0.0
    has_harm = sw[HARMONICS] != 0
    has_dist = enabled and sw[DISTORTION] != 0
    lagged = enabled and sw[LAGGED] != 0
    # PI loops on R-L phases: the lag's constants are then each phase's bandwidth ωb
    # (rad/s), R/L and 1/L, and T_A, T_B hold the loops' integrators.
    pi_loop = lagged and sw[PI_LOOP] != 0
    dead_time = enabled and sw[DEAD_TIME] != 0
    dead, inv_knee = c[DEAD], c[INV_KNEE]
    coulomb_l = sw[COULOMB_L] != 0
    beyond = sw[BEYOND] != 0
    reshaping = sw[RESHAPING] != 0
    saturating = sw[SATURATING] != 0
    detent_alone = sw[DETENT_ALONE] != 0
    eccentric = sw[ECCENTRIC] != 0
    drifting = sw[DRIFTING] != 0
    kx, p0, pv, pa = cmd[KX], cmd[P0], cmd[PV], cmd[PA]
    off_a, off_b, fa, fb = cmd[OFF_A], cmd[OFF_B], cmd[FA], cmd[FB]
    la0, la1, la2, lb0, lb1, lb2 = c[LA0], c[LA1], c[LA2], c[LB0], c[LB1], c[LB2]
    cv0, cp0, cn0, iw0 = c[CV0], c[CP0], c[CN0], c[IW0]
    cvl, cpl, cnl, iwl = c[CVL], c[CPL], c[CNL], c[IWL]
    j0, j1, jl = c[J0], c[J1], c[JL]
    k1, c1, n1, k2, c2, n2 = c[K1], c[C1], c[N1], c[K2], c[C2], c[N2]
    r_over_h, inv_isat2 = c[R_OVER_H], c[INV_ISAT2]
    ecc, ecc_phase, unb, unb_phase = c[ECC], c[ECC_PHASE], c[UNB], c[UNB_PHASE]
    if enabled:
        i_a, i_b, t_a, t_b = state[I_A], state[I_B], state[T_A], state[T_B]
    else:
        i_a = i_b = t_a = t_b = 0.0
    th0, om0, th1, om1 = state[TH0], state[OM0], state[TH1], state[OM1]
    thl, oml = state[THL], state[OML]
    acc0 = acc1 = 0.0
    tau = tau_em = 0.0
    for k in range(steps.shape[0]):
        t, w0, w1 = steps[k, 0], steps[k, 1], steps[k, 2]
        te = nr * th0
        s1 = math.sin(te)
        co1 = math.cos(te)
        # Drive: phase currents from the position demand at this instant.
        if enabled:
            x = kx * (p0 + (pv + pa * t) * t)
            ua = off_a + fa * math.cos(x)
            ub = off_b + fb * math.sin(x)
            if has_dist:
                ua += fa * _table(distortion[0], x, tscale, size)
                ub += fb * _table(distortion[1], x, tscale, size)
            if dead_time:
                # The bridge's dead time: a current error of fixed size against the
                # current's sign, turning over the PWM ripple's width (the knee).
                ua -= dead * math.tanh(ua * inv_knee)
                ub -= dead * math.tanh(ub * inv_knee)
            if pi_loop:
                # L·i' = Kp(u − i) + Ki·z − R·i − e, z' = u − i, tuned Kp = ωb·L and
                # Ki = ωb·R (the zero on the phase's pole: u to i is a first-order lag),
                # e the back-EMF ω·∂τ/∂i; implicit in i, then the integrator.
                ea = -kt * s1
                eb = kt * co1
                if has_harm:
                    ea += _table(harmonics[0], te, tscale, size)
                    eb += _table(harmonics[1], te, tscale, size)
                i_a = (i_a + h * (la0 * (ua + la1 * t_a) - la2 * om0 * ea)) / (
                    1.0 + h * (la0 + la1))
                i_b = (i_b + h * (lb0 * (ub + lb1 * t_b) - lb2 * om0 * eb)) / (
                    1.0 + h * (lb0 + lb1))
                t_a += h * (ua - i_a)
                t_b += h * (ub - i_b)
            elif lagged:
                i_a = la0 * i_a + la1 * t_a + la2 * ua
                i_b = lb0 * i_b + lb1 * t_b + lb2 * ub
                t_a = ua
                t_b = ub
            else:
                i_a = ua
                i_b = ub
        # Motor: eq. (1) for the fundamental, then whatever the unit adds.
        tau = kt * (i_b * co1 - i_a * s1)
        if has_harm:
            tau += i_a * _table(harmonics[0], te, tscale, size)
            tau += i_b * _table(harmonics[1], te, tscale, size)
            tau += _table(harmonics[2], te, tscale, size)
        if beyond:
            if not reshaping:
                tau += rel * (2.0 * (co1 * co1 - s1 * s1) * i_a * i_b
                              - 2.0 * s1 * co1 * (i_a * i_a - i_b * i_b))
                if rel_u != 0.0:
                    tau -= rel_u * 2.0 * s1 * co1 * (i_a * i_a + i_b * i_b)
            else:
                # τ is the magnet's so far (detent has its own table here):
                # m(θ)·(g(|i|)·τ_pm + τ_cg + τ_vr), then the unbalance's load
                # (motor.py). ``tau`` drives the rotor, ``tau_em`` is reported.
                if saturating:
                    tau /= math.sqrt(1.0 + (i_a * i_a + i_b * i_b) * inv_isat2)
                if detent_alone:
                    tau += _table(detent, te, tscale, size)
                if rel != 0.0:
                    tau += rel * (2.0 * (co1 * co1 - s1 * s1) * i_a * i_b
                                  - 2.0 * s1 * co1 * (i_a * i_a - i_b * i_b))
                    if rel_u != 0.0:
                        tau -= rel_u * 2.0 * s1 * co1 * (i_a * i_a + i_b * i_b)
                if eccentric:
                    tau *= 1.0 + ecc * math.cos(th0 + ecc_phase)
                    tau_em = tau
                    tau -= unb * math.sin(th0 + unb_phase)
                else:
                    tau_em = tau
        # Mechanics: friction implicit (linearised), springs explicit.
        tf = math.tanh(om0 * iw0)
        cc = cp0 if om0 >= 0.0 else cn0
        f0 = cv0 * om0 + cc * tf
        df0 = cv0 + cc * iw0 * (1.0 - tf * tf)
        if ndof == 1:
            new0 = om0 + h * (tau - f0) / (j0 + h * df0)
            u = (new0 - om0) * r_over_h
            om0 = new0
            th0 += h * new0
        else:
            if coulomb_l:
                tl = math.tanh(oml * iwl)
                ccl = cpl if oml >= 0.0 else cnl
                fl = cvl * oml + ccl * tl
                dfl = cvl + ccl * iwl * (1.0 - tl * tl)
            else:
                fl = cvl * oml
                dfl = cvl
            if ndof == 2:
                ts = k1 * (n1 * th0 - thl) + c1 * (n1 * om0 - oml)
                new0 = om0 + h * (tau - n1 * ts - f0) / (j0 + h * df0)
                newl = oml + h * (ts - fl) / (jl + h * dfl)
            else:
                ts = k1 * (n1 * th0 - th1) + c1 * (n1 * om0 - om1)
                ts2 = k2 * (n2 * th1 - thl) + c2 * (n2 * om1 - oml)
                new0 = om0 + h * (tau - n1 * ts - f0) / (j0 + h * df0)
                om1 += h * (ts - n2 * ts2) / j1
                th1 += h * om1
                newl = oml + h * (ts2 - fl) / (jl + h * dfl)
            u = (newl - oml) * r_over_h
            om0 = new0
            th0 += h * new0
            oml = newl
            thl += h * newl
        # Sensor front end: its analog low-pass sees r·α continuously.
        acc0 += w0 * u
        acc1 += w1 * u
        if drifting:
            u_out[k] = u
    if ndof == 1:
        thl, oml = th0, om0
    state[TH0], state[OM0], state[TH1], state[OM1] = th0, om0, th1, om1
    state[THL], state[OML] = thl, oml
    state[I_A], state[I_B] = i_a, i_b
    if lagged:
        state[T_A], state[T_B] = t_a, t_b
    else:
        state[T_A], state[T_B] = i_a, i_b
    state[ACC0], state[ACC1] = acc0, acc1
    state[TORQUE] = tau_em if reshaping else tau
