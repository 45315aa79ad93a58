"""Pseudo-rigid-body links: pressure tables, inflatable-beam limits, link dynamics with hysteresis, play/PI.

Seed 001 models an inflatable link as two rigid bodies joined by a virtual hinge with a torsional spring and
damper, eq. (2): I δ̈ + c(p) δ̇ + k(p) δ = τ. We add the non-linear range above the wrinkling moment M_w that
Fig. 7 shows: a softening towards the collapse moment M_c, and a Bouc–Wen offset to the spring, k (δ + δ_h z),
driven by the moment in excess of M_w, for the static hysteresis (loop ≈ 2 δ_h once well past M_w). SI units,
float64 throughout.

Functions marked (K) are "ufunc-style": the twin compiles them with ``numba.njit`` and calls them on scalar
float64 inside its time loop, while tests and analysis call the same functions on numpy arrays. They therefore
use only arithmetic and numpy ufuncs, no ``if`` on values, no np.clip/np.where, and never call another
function of this module (numba cannot call a plain Python function), which is why a few lines repeat.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

Float = float | NDArray[np.float64]

GAMMA_HOWELL = 0.85  # characteristic radius factor: virtual joint at (1 − γ) L from the clamped end
K_THETA_HOWELL = 2.65  # stiffness coefficient: spring K = γ K_Θ E I / L

WRINKLE_X_MAX = 0.95  # wrinkled compliance held at 95 % of the way from M_w to M_c (collapse: infinite)
_TINY = 1e-150  # keeps sin(s dt)/s and expm1(−2 s dt)/(2 s) finite at s = 0 (their limit is dt)


# ------------------------------------------------------------------------------------------ pressure tables
def interp_table(p: ArrayLike, p_table: ArrayLike, values: ArrayLike) -> NDArray[np.float64]:
    """Linear interpolation of a per-pressure table at pressures ``p`` (any shape).

    Outside the table the end values are held (clamped), not extrapolated: a link is never assumed stiffer or
    softer than measured. ``p_table`` must be strictly increasing and the same length as ``values``.
    """
    xp = np.asarray(p_table, dtype=np.float64)
    fp = np.asarray(values, dtype=np.float64)
    if xp.ndim != 1 or fp.shape != xp.shape or xp.size == 0:
        raise ValueError(f"p_table and values must be 1-D of equal length, got {xp.shape} and {fp.shape}")
    if np.any(np.diff(xp) <= 0):
        raise ValueError("p_table must be strictly increasing")
    return np.asarray(np.interp(np.asarray(p, dtype=np.float64), xp, fp), dtype=np.float64)


def interp_table_scalar(p: float, p_table: NDArray[np.float64], values: NDArray[np.float64]) -> float:
    """(K, scalar p only) :func:`interp_table` for one pressure as a plain loop numba compiles; clamped."""
    n = p_table.shape[0]
    if p <= p_table[0]:
        return values[0] * 1.0
    for i in range(n - 1):
        if p <= p_table[i + 1]:
            w = (p - p_table[i]) / (p_table[i + 1] - p_table[i])
            return values[i] + w * (values[i + 1] - values[i])
    return values[n - 1] * 1.0


# ---------------------------------------------------------------------------------- inflatable-beam limits
def collapse_moment(p: Float, r: Float) -> Float:
    """(K) Collapse moment M_c = (π²/4) p r³ of an inflated beam (seed 001 eq. 1); p is gauge pressure."""
    return (np.pi**2 / 4.0) * p * r**3


def wrinkling_moment(p: Float, r: Float) -> Float:
    """(K) Wrinkling moment M_w = M_c / 2: above it the link is non-linear (raise a wrinkling alarm)."""
    return (np.pi**2 / 8.0) * p * r**3


# ------------------------------------------------------------------------------------------ modal relations
def damped_frequency_hz(k: Float, c: Float, inertia: Float) -> Float:
    """(K) Damped natural frequency sqrt(k/I − (c/2I)²)/2π [Hz]; 0 when critically or over-damped."""
    a = c / (2.0 * inertia)
    return np.sqrt(np.maximum(k / inertia - a * a, 0.0)) / (2.0 * np.pi)


def inertia_from_damped_frequency(k: Float, c: Float, f_s: Float) -> Float:
    """(K) Inertia I giving damped frequency f_s with k, c: the lightly-damped root of ω²I² − kI + c²/4 = 0.

    NaN when no inertia can reach f_s (k < 2π f_s c).
    """
    w2 = (2.0 * np.pi * f_s) ** 2
    return (k + np.sqrt(k * k - w2 * c * c)) / (2.0 * w2)


def damping_from_ratio(zeta: Float, k: Float, inertia: Float) -> Float:
    """(K) Damping coefficient c = 2 ζ sqrt(k I) [N·m·s/rad] for a damping ratio ζ."""
    return 2.0 * zeta * np.sqrt(k * inertia)


def damping_ratio(k: Float, c: Float, inertia: Float) -> Float:
    """(K) Damping ratio ζ = c / (2 sqrt(k I))."""
    return c / (2.0 * np.sqrt(k * inertia))


# ------------------------------------------------------------------------------- hysteresis and link steps
def bouc_wen_step(z: Float, dtorque: Float, tau_y: Float) -> Float:
    """(K) Advance the Bouc–Wen state z by a torque increment dτ (A = 1, β = γ = 0.5, n = 1), |z| ≤ 1.

    Solves dz = [1 − (0.5 sgn(dτ z) + 0.5)|z|] dτ/τ_y exactly for a monotone dτ (linear towards 0, then
    exponential towards sgn(dτ)), so the result does not depend on how finely the torque is sampled.
    """
    g = dtorque / tau_y
    s = np.sign(g)
    z = np.minimum(np.maximum(z, -1.0), 1.0)
    lin = np.minimum(np.abs(g), np.maximum(-s * z, 0.0))  # linear part while moving back towards z = 0
    z0 = z + s * lin
    return z0 + s * (1.0 - s * z0) * (-np.expm1(lin - np.abs(g)))


def link_step(
    delta: Float,
    delta_dot: Float,
    z: Float,
    torque: Float,
    load: Float,
    load_prev: Float,
    k: Float,
    c: Float,
    inertia: Float,
    delta_h: Float,
    tau_y: Float,
    m_w: Float,
    dt: float,
) -> tuple[Float, Float, Float]:
    """(K) One step of I δ̈ + c δ̇ + k (δ − w(M) + δ_h z) = τ (eq. 2 with wrinkling and hysteresis); (δ, δ̇, z).

    ``torque`` τ is the whole moment about the virtual joint (gravity, payload and the drives' accelerations);
    ``load`` M is its static part (gravity and payload), ``load_prev`` M one step before. M alone drives the
    quasi-static terms, so the drives' ringing neither relaxes the hysteresis nor wrinkles the link:

    - hysteresis: z advances by the change of :func:`hysteresis_input` (Bouc–Wen, :func:`bouc_wen_step`);
    - wrinkling: :func:`wrinkle_deflection` w(M) adds the compliance of the wrinkled section above M_w.

    ``m_w`` is the link's wrinkling moment M_w(p); m_w ≤ 0 marks a link that is not an inflatable beam (its
    hysteresis acts over the whole range, it never wrinkles). δ is then updated by the exact solution of the
    linear part with τ, z and w held over the step (zero-order hold): exact frequency and decay, stable for
    any dt, k > 0, I > 0, c ≥ 0 (under-, critically and over-damped). At rest δ = τ/k + w − δ_h z, so the
    loading branch lies δ_h below the elastic line, the unloading branch δ_h above. δ_h = 0 and m_w = 0: a
    plain spring-damper.
    """
    # hysteresis input, same lines as hysteresis_input (numba cannot call it)
    onset = np.maximum(m_w, 0.0)
    e_now = np.sign(load) * np.maximum(np.abs(load) - onset, 0.0)
    e_prev = np.sign(load_prev) * np.maximum(np.abs(load_prev) - onset, 0.0)
    # Bouc–Wen update, same lines as bouc_wen_step
    g = (e_now - e_prev) / tau_y
    s = np.sign(g)
    z = np.minimum(np.maximum(z, -1.0), 1.0)
    lin = np.minimum(np.abs(g), np.maximum(-s * z, 0.0))
    z0 = z + s * lin
    z_new = z0 + s * (1.0 - s * z0) * (-np.expm1(lin - np.abs(g)))
    # wrinkled compliance, same lines as wrinkle_deflection
    inflatable = (m_w > 0.0) * 1.0
    scale = np.maximum(m_w, _TINY)
    x = inflatable * np.minimum(np.maximum(np.abs(load) - scale, 0.0) / scale, WRINKLE_X_MAX)
    wrinkle = np.sign(load) * scale / k * (-np.log1p(-x) - x)
    # Exact free response of e = δ − δ_eq: e'' + 2a e' + wn2 e = 0, with x(dt) = C e0 + S (v0 + a e0) and
    # v(dt) = C v0 − S (a v0 + wn2 e0), where C, S include the decay e^(−a dt).
    delta_eq = torque / k + wrinkle - delta_h * z_new
    e0 = delta - delta_eq
    a = c / (2.0 * inertia)
    wn2 = k / inertia
    w2 = wn2 - a * a
    sd = np.maximum(np.sqrt(np.abs(w2)), _TINY)
    under = (w2 >= 0.0) * 1.0
    decay = np.exp(-a * dt)
    slow = np.exp(-wn2 / (a + sd) * dt)  # over-damped slow mode e^(−(a − s) dt), written without cancellation
    c_u = decay * np.cos(sd * dt)
    s_u = decay * np.sin(sd * dt) / sd
    c_o = slow * 0.5 * (1.0 + np.exp(-2.0 * sd * dt))
    s_o = slow * (-np.expm1(-2.0 * sd * dt)) / (2.0 * sd)
    cc = under * c_u + (1.0 - under) * c_o
    ss = under * s_u + (1.0 - under) * s_o
    e1 = cc * e0 + ss * (delta_dot + a * e0)
    v1 = cc * delta_dot - ss * (a * delta_dot + wn2 * e0)
    return delta_eq + e1, v1, z_new


def hysteresis_input(load: Float, m_w: Float) -> Float:
    """(K) The moment that drives an inflatable link's hysteresis: its excess over the wrinkling moment,
    sgn(M) max(|M| − M_w, 0). Seed 001 finds the link linear below M_w (its static k is the dynamic k̂
    within 8 %); the loop of Fig. 7 comes from the wrinkles forming and closing above it, and leaves a
    residual deflection once they close. m_w ≤ 0 (not an inflatable beam): M itself."""
    onset = np.maximum(m_w, 0.0)
    return np.sign(load) * np.maximum(np.abs(load) - onset, 0.0)


def wrinkle_deflection(load: Float, k: Float, m_w: Float) -> Float:
    """(K) Extra deflection of a wrinkled inflatable link under a static moment M beyond M_w.

    Above M_w the wrinkled part of the wall carries no tension and the section stiffens less and less; we
    let the tangent stiffness fall linearly from k at M_w to 0 at the collapse moment M_c = 2 M_w (eq. 1):
    dM/dδ = k (1 − x), x = (|M| − M_w)/(M_c − M_w). Integrated: w = sgn(M) (M_w/k) (−ln(1 − x) − x), 0 below
    M_w, with a continuous slope there; x is held at :data:`WRINKLE_X_MAX`. m_w ≤ 0: 0 (not inflatable).
    """
    inflatable = (m_w > 0.0) * 1.0
    scale = np.maximum(m_w, _TINY)
    x = inflatable * np.minimum(np.maximum(np.abs(load) - scale, 0.0) / scale, WRINKLE_X_MAX)
    return np.sign(load) * scale / k * (-np.log1p(-x) - x)


def static_deflection(torque: Float, k: Float, delta_h: Float = 0.0, z: Float = 0.0) -> Float:
    """(K) Deflection at rest δ = τ/k − δ_h z."""
    return torque / k - delta_h * z


def static_loading_curve(
    torques: ArrayLike, k: ArrayLike, delta_h: ArrayLike, tau_y: ArrayLike, m_w: ArrayLike = 0.0
) -> NDArray:
    """Quasi-static deflections along a torque sequence (seed 001 Fig. 7: loading then unloading).

    ``torques`` has time first, (T,) or (T, B); k, δ_h, τ_y and the wrinkling moment m_w broadcast against
    the batch, e.g. k of shape (B,) for B pressures; m_w = 0: not an inflatable beam (hysteresis over the
    whole range, no wrinkling), as in :func:`link_step`. The link starts virgin (z = 0 at τ = 0). Returns δ of
    shape (T, *batch): τ/k + w(τ) − δ_h z.
    """
    tq = np.asarray(torques, dtype=np.float64)
    k, delta_h, tau_y, m_w = (np.asarray(v, dtype=np.float64) for v in (k, delta_h, tau_y, m_w))
    batch = np.broadcast_shapes(tq.shape[1:], k.shape, delta_h.shape, tau_y.shape, m_w.shape)
    out = np.empty(tq.shape[:1] + batch, dtype=np.float64)
    z = np.zeros(batch)
    prev = np.zeros(batch)
    for t in range(tq.shape[0]):
        e = hysteresis_input(tq[t], m_w)
        z = bouc_wen_step(z, e - prev, tau_y)
        prev = e
        out[t] = tq[t] / k + wrinkle_deflection(tq[t], k, m_w) - delta_h * z
    return out


# ------------------------------------------------------------------------- play operator / Prandtl–Ishlinskii
def play(x: Float, y_prev: Float, r: Float) -> Float:
    """(K) Play (backlash) operator y = max(x − r, min(x + r, y_prev)); gear backlash b (total) is r = b/2."""
    return np.maximum(x - r, np.minimum(x + r, y_prev))


class PrandtlIshlinskii:
    """Prandtl–Ishlinskii hysteresis: y = Σ wᵢ playᵢ(x) over play operators of radii rᵢ ≥ 0."""

    def __init__(self, radii: ArrayLike, weights: ArrayLike) -> None:
        r = np.array(radii, dtype=np.float64)
        w = np.array(weights, dtype=np.float64)
        if r.ndim != 1 or w.shape != r.shape or r.size == 0:
            raise ValueError(f"radii and weights must be 1-D of equal length, got {r.shape}, {w.shape}")
        if not (np.all(np.isfinite(r)) and np.all(np.isfinite(w))):
            raise ValueError("radii and weights must be finite")
        if np.any(r < 0):
            raise ValueError("radii must be >= 0")
        r.flags.writeable = False
        w.flags.writeable = False
        self.radii = r
        self.weights = w

    def apply(self, x: ArrayLike) -> NDArray[np.float64]:
        """Output for an input history x of shape (T, ...), time first; every play state starts at 0."""
        xs = np.asarray(x, dtype=np.float64)
        state = np.zeros(xs.shape[1:] + self.radii.shape)
        y = np.empty(xs.shape, dtype=np.float64)
        for t in range(xs.shape[0]):
            state = play(xs[t][..., None], state, self.radii)
            y[t] = state @ self.weights
        return y

    def max_loop_width(self) -> float:
        """Vertical width 2 Σ wᵢ rᵢ of the major loop, reached once the input's excursion is ≥ 4 max rᵢ."""
        return float(2.0 * np.sum(self.weights * self.radii))


def loop_width(x: ArrayLike, y: ArrayLike) -> float:
    """Largest vertical gap |y_down − y_up| of one hysteresis loop: x rises to its maximum, then falls.

    The branches are compared where both cover x (linear interpolation); used for Fig. 7 and PI loops.
    """
    xs = np.asarray(x, dtype=np.float64)
    ys = np.asarray(y, dtype=np.float64)
    i = int(np.argmax(xs))
    x_up, y_up = xs[: i + 1], ys[: i + 1]
    x_dn, y_dn = xs[i:][::-1], ys[i:][::-1]
    if np.any(np.diff(x_up) < 0) or np.any(np.diff(x_dn) < 0):
        raise ValueError("x must rise monotonically to its maximum and then fall monotonically")
    grid = np.unique(np.concatenate([x_up, x_dn]))
    grid = grid[(grid >= max(x_up[0], x_dn[0])) & (grid <= xs[i])]
    return float(np.max(np.abs(np.interp(grid, x_dn, y_dn) - np.interp(grid, x_up, y_up))))


# ------------------------------------------------------------------------- Howell's pseudo-rigid cantilever
def prbm_tip(length: Float, gamma: Float, theta: Float) -> tuple[Float, Float]:
    """(K) Tip of a PRBM cantilever at virtual-joint angle Θ: (a, b) = (L[1 − γ(1 − cos Θ)], γ L sin Θ)."""
    return length * (1.0 - gamma * (1.0 - np.cos(theta))), gamma * length * np.sin(theta)


def cantilever_torque(force: Float, length: Float, gamma: Float, theta: Float) -> Float:
    """(K) Moment F γ L cos Θ about the virtual hinge of a tip force perpendicular to the undeformed link."""
    return force * gamma * length * np.cos(theta)
