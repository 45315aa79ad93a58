"""Seed 001's link tests on the POPUP arm, measured: the static characteristic (``popup_static`` sessions:
τ against δ per pressure, the static stiffness k), the free oscillation after each tap (``popup_impact``:
damped frequency f_s and damping ratio ζ) and Table 1's estimates (k̂, ĉ, the link's inertia I). The report
(``analysis.popup_tests``: the paper's values beside ours, Figure 7) and the twin's fit of the POPUP arm
(``pipeline.popup_fit``) read them.

Conventions (SI inside, degrees and kPa only for display):
- PRBM of the link under test (link 2): a virtual hinge at distance ``l1`` from the link's root, the load at
  the tip, ``arm`` = l2 = hinge → tip. The paper sets l1 = 30 mm, l2 = 570 mm on its 600 mm prototype;
  the twin's link 2 has its hinge (D-H joint d22) 590 mm from the tip, so by default ``arm`` is read from
  the robot description (the hinge row's a_m, 0.590 m for the twin); ``arm_m=PAPER_L2_M`` uses the paper's.
- τ = load · g · arm + the link's own moment about the hinge (every mass carried on the hinge's frame);
  δ = v / arm with v the tip's downward displacement from the session's first hold (the unloaded link under
  its own weight), so curves start at (0, own moment).
"""

from __future__ import annotations

import itertools
from pathlib import Path

import numpy as np
import pandas as pd
from scipy import optimize, signal

from models import prbm
from models.robot import RobotDescription
from pipeline.errors import PipelineError
from pipeline.ingest import DAMAGED_CHUNKS, ingest_session
from pipeline.tables import EventKind, SessionTables

G = 9.81
PAPER_L1_M, PAPER_L2_M = 0.030, 0.570  # seed 001 Sec. 4: PRBM body lengths of the 600 mm link
TRACKER, ACCEL = "/tracker/pose", "/imu/accel"
BRANCHES = ("loading", "unloading")
TAP_SKIP_S = 0.02  # after a tap: skip the hammer contact before the free oscillation
PEAK_FLOOR = 0.05  # the free oscillation is fitted from its largest peak down to 5 % of it (above the noise)
NFFT = 2**17  # zero padding of the PSD (the fit's starting frequency): 1 kHz / 2^17 ≈ 0.008 Hz bins


class LinkTestError(PipelineError, ValueError):
    """A link test's session that cannot be measured: damaged, or without the stream or events it needs."""


def _ingested(directory: Path, stream: str) -> SessionTables:
    """The session's tables; :class:`LinkTestError` naming the session where a chunk was left out as damaged
    (a link test's numbers are not taken from part of its samples) or ``stream`` has no sample."""
    st = ingest_session(directory)
    if damaged := st.report.values.get(DAMAGED_CHUNKS):
        raise LinkTestError(f"session {Path(directory).name}: damaged ({damaged[0]})")
    if stream not in st.streams or not len(st.streams[stream]):
        raise LinkTestError(f"session {Path(directory).name}: no {stream} samples")
    return st


def _seconds(log_time) -> np.ndarray:
    return np.asarray(log_time, np.int64) * 1e-9


def link_hinge(robot: RobotDescription, link: str = "link2") -> tuple[str, float]:
    """(frame, arm m) of ``link``'s hinge: its last virtual joint, and that D-H row's a_m (hinge → tip); the
    masses on that frame are what the tests load and swing."""
    spec = next(lk for lk in robot.links if lk.name == link)
    hinge = spec.virtual_joints[-1]
    return hinge, float(next(r.a_m for r in robot.kinematics.rows if r.joint == hinge))


def link_geometry(robot: RobotDescription, link: str = "link2") -> tuple[float, float, float]:
    """(arm m, own moment N·m, radius m) of ``link``: its hinge's arm (:func:`link_hinge`), the moment of the
    masses on the hinge's frame about the hinge, and the link radius."""
    hinge, arm = link_hinge(robot, link)
    own = sum(m.mass_kg * G * (arm + m.position_m[0]) for m in robot.masses if m.frame == hinge)
    radius = next(lk.radius_m for lk in robot.links if lk.name == link)
    return arm, float(own), float(radius)


def _hold_means(t: np.ndarray, x: np.ndarray, t0: np.ndarray, t1: np.ndarray) -> np.ndarray:
    """Mean of x over each window [t0, t1) (t sorted), vectorised with cumulative sums."""
    csum = np.concatenate([[0.0], np.cumsum(x)])
    i0, i1 = np.searchsorted(t, t0), np.searchsorted(t, t1)
    return (csum[i1] - csum[i0]) / np.maximum(i1 - i0, 1)


def static_holds(directory: Path, link: str | None = None, arm_m: float | None = None) -> pd.DataFrame:
    """One row per SETTLED hold of a popup_static session: rep, branch, load, tip displacement, τ, δ of
    ``link`` (default: the link the session's plan loaded, its ``link`` parameter; link 2 if it has none)."""
    st = _ingested(directory, TRACKER)
    link = link or st.parameters.get("link", "link2")
    ev = st.events
    arm, own, radius = link_geometry(st.robot, link)
    arm = arm if arm_m is None else arm_m
    pressure = float(st.parameters["pressure_pa"])
    t_ev = _seconds(ev["log_time"])
    steps = ev[(ev["kind"] == EventKind.PLAN_STEP) & ev["label"].isin(BRANCHES)]
    pay = ev[ev["kind"] == EventKind.PAYLOAD]
    settled = ev["kind"].to_numpy() == EventKind.SETTLED
    t0 = t_ev[settled]
    hold = ev.loc[settled, "value"].to_numpy()
    i_step = np.searchsorted(_seconds(steps["log_time"]), t0, side="right") - 1
    i_pay = np.searchsorted(_seconds(pay["log_time"]), t0, side="right") - 1
    tr = st.streams[TRACKER]
    ok = ~tr["missing"].to_numpy(bool)
    z = _hold_means(_seconds(tr["log_time"])[ok], tr["position_2"].to_numpy()[ok], t0, t0 + hold)
    load = pay["value"].to_numpy()[i_pay]
    v = z[0] - z  # downward tip displacement from the first hold (tracker z is vertical)
    return pd.DataFrame(
        {
            "session_id": st.session_id,
            "robot": st.robot.name,
            "link": link,
            "pressure_pa": pressure,
            "rep": steps["index"].to_numpy()[i_step],
            "branch": steps["label"].to_numpy()[i_step],
            "point": ev.loc[settled, "index"].to_numpy(),
            "load_kg": np.round(load, 6),
            "displacement_m": v,
            "torque_nm": load * G * arm + own,
            "delta_rad": v / arm,
            "arm_m": arm,
            "wrinkling_moment_nm": prbm.wrinkling_moment(pressure, radius),
        }
    )


def link_static_curves(
    sessions: list[Path], link: str | None = None, arm_m: float | None = None
) -> pd.DataFrame:
    """Mean (and std over the repetitions) static characteristic per pressure, branch and load: τ, δ, v.

    Rows are in test order (loading up, unloading down); ``attrs['sessions']`` names the sessions used."""
    return static_curves(pd.concat([static_holds(s, link, arm_m) for s in sessions], ignore_index=True))


def static_curves(holds: pd.DataFrame) -> pd.DataFrame:
    """:func:`link_static_curves` of the holds of its sessions (:func:`static_holds`, concatenated)."""
    holds = holds.copy()
    holds["order"] = holds.groupby(["pressure_pa", "rep"]).cumcount()
    keys = ["pressure_pa", "branch", "load_kg"]
    g = holds.groupby(keys, sort=False)
    curves = g.agg(
        order=("order", "min"),
        torque_nm=("torque_nm", "mean"),
        delta_rad=("delta_rad", "mean"),
        delta_std_rad=("delta_rad", "std"),
        displacement_m=("displacement_m", "mean"),
        displacement_std_m=("displacement_m", "std"),
        n_runs=("rep", "nunique"),
        arm_m=("arm_m", "first"),
        wrinkling_moment_nm=("wrinkling_moment_nm", "first"),
    ).reset_index()
    curves = curves.sort_values(["pressure_pa", "order"], ignore_index=True).drop(columns="order")
    curves.attrs["sessions"] = sorted(holds["session_id"].unique().tolist())
    return curves


def static_stiffness(curves: pd.DataFrame, branch: str = "loading") -> pd.DataFrame:
    """Per pressure, k [N·m/rad] = slope of τ on δ over the mean points of ``branch`` below M_w(p).

    Seed 001 fitted k on its first static tests, which only loaded the link (the unloading branch came with
    the later hysteresis study); the loading branch is also the one free of the residual deflection the
    wrinkles leave. ``branch=None`` fits both branches together."""
    rows = []
    for p, c in curves.groupby("pressure_pa"):
        lin = c[(c["torque_nm"] < c["wrinkling_moment_nm"]) & ((c["branch"] == branch) if branch else True)]
        if lin["load_kg"].nunique() < 2:
            continue
        k, b = np.polyfit(lin["delta_rad"], lin["torque_nm"], 1)
        rows.append({"pressure_pa": p, "k": k, "intercept_nm": b, "n_points": len(lin),
                     "wrinkling_moment_nm": c["wrinkling_moment_nm"].iloc[0]})  # fmt: skip
    return pd.DataFrame(rows)


def elastic_stiffness(curves: pd.DataFrame) -> pd.DataFrame:
    """Per pressure, the link's elastic stiffness k [N·m/rad] and its standard error: the slope of τ on δ
    over both branches' mean points below M_w(p), each branch with an intercept of its own. The loop's
    offset between the branches (the hysteresis) cancels, which the loading branch alone cannot do: on the
    twin its slope is ~0.5 % low. A pressure with fewer than two loads on each branch has none."""
    rows = []
    for p, c in curves.groupby("pressure_pa"):
        lin = c[c["torque_nm"] < c["wrinkling_moment_nm"]]
        if (lin.groupby("branch")["load_kg"].nunique().reindex(list(BRANCHES)).fillna(0) < 2).any():
            continue
        x = np.column_stack([lin["delta_rad"], *(lin["branch"].eq(b).astype(float) for b in BRANCHES)])
        y = lin["torque_nm"].to_numpy()
        coef, *_ = np.linalg.lstsq(x, y, rcond=None)
        dof = len(y) - x.shape[1]
        sigma2 = float(np.sum((y - x @ coef) ** 2) / dof) if dof > 0 else np.nan
        se = float(np.sqrt(sigma2 * np.linalg.inv(x.T @ x)[0, 0])) if dof > 0 else np.nan
        rows.append({"pressure_pa": p, "k": float(coef[0]), "k_se": se, "n_points": len(lin)})
    return pd.DataFrame(rows, columns=["pressure_pa", "k", "k_se", "n_points"])


def _device_time(acc: pd.DataFrame) -> np.ndarray:
    """Accelerometer sample times on the host timeline: the device's micros (unwrapped, jitter-free) mapped by
    a least-squares line onto host log times (removes the device clock's offset and drift)."""
    us = np.unwrap(acc["micros"].to_numpy(np.float64), period=2.0**32) * 1e-6
    host = _seconds(acc["log_time"])
    a, b = np.polyfit(us - us[0], host - host[0], 1)
    return host[0] + b + a * (us - us[0])


def free_oscillation(t: np.ndarray, a: np.ndarray, fs: float) -> tuple[float, float]:
    """(f_s Hz, ζ) of one free oscillation: a damped sinusoid fitted by least squares to the principal
    acceleration component, from its largest peak until the peaks fall to ``PEAK_FLOOR`` of it.

    x(t) = e^(−σt) (A cos ω_d t + B sin ω_d t) + C; for each (σ, ω_d) the amplitudes are linear, so only σ and
    ω_d are searched (variable projection), started from the PSD peak and the peaks' log decrement. Then
    f_s = ω_d / 2π is the damped frequency itself and ζ = σ / √(σ² + ω_d²). The PSD peak alone is not f_s:
    an acceleration's spectrum peaks above the damped frequency by a bias that grows as ζ² (+1.4 % at
    ζ = 0.17), which is why the fit, not the peak, is the estimate."""
    x = a - a.mean(axis=0)
    x = x @ np.linalg.svd(x, full_matrices=False)[2][0]
    f, psd = signal.welch(x, fs=fs, window="boxcar", nperseg=len(x), nfft=max(NFFT, len(x)), detrend=False)
    f_peak = float(f[np.argmax(psd)])
    cycle = max(int(0.7 * fs / f_peak), 1)  # one peak per sign and cycle
    ext = np.sort(np.concatenate([signal.find_peaks(sx, distance=cycle)[0] for sx in (x, -x)]))
    amp, t_ext = np.abs(x[ext]), t[ext]
    first = np.argmax(amp)
    low = np.flatnonzero(amp[first:] < PEAK_FLOOR * amp[first])
    last = first + (low[0] if len(low) else len(amp) - first)
    decay = max(-np.polyfit(t_ext[first:last], np.log(amp[first:last]), 1)[0], 0.0)  # envelope e^(−σ t)
    window = slice(ext[first], ext[last - 1] + 1)
    tw, xw = t[window] - t[ext[first]], x[window]

    def residual(params: np.ndarray) -> np.ndarray:
        sigma, omega = params
        envelope = np.exp(-sigma * tw)
        basis = np.column_stack(
            [envelope * np.cos(omega * tw), envelope * np.sin(omega * tw), np.ones_like(tw)]
        )
        coef = np.linalg.lstsq(basis, xw, rcond=None)[0]
        return basis @ coef - xw

    omega = 2 * np.pi * f_peak
    fit = optimize.least_squares(residual, [decay, omega], x_scale=[1.0, omega],
                                 bounds=([0.0, omega / 4], [np.inf, 2 * omega]))  # fmt: skip
    sigma, omega = fit.x
    return float(omega / (2 * np.pi)), float(sigma / np.hypot(sigma, omega))


def impacts(t: np.ndarray, a: np.ndarray, marks: np.ndarray) -> np.ndarray:
    """The time of each hammer impact: the strongest acceleration (off the session's median, any axis) nearer
    its tap event than any other. The event marks when the operator was asked to tap, or when the runner
    logged it after the rig's tap returned (up to 55 ms late on a busy host, measured): the impact itself is
    in the data."""
    x = np.linalg.norm(a - np.median(a, axis=0), axis=1)
    bounds = np.concatenate([[-np.inf], (marks[1:] + marks[:-1]) / 2, [np.inf]])
    out = np.empty(len(marks))
    for i, (lo, hi) in enumerate(itertools.pairwise(bounds)):
        near = np.flatnonzero((t >= lo) & (t < hi))
        out[i] = t[near[np.argmax(x[near])]] if near.size else marks[i]
    return out


def impact_taps(directory: Path) -> pd.DataFrame:
    """One row per tap of a popup_impact session: f_s and ζ of the free oscillation that follows its impact,
    up to the next one."""
    st = _ingested(directory, ACCEL)
    ev = st.events
    tapped = (ev["kind"] == EventKind.PLAN_STEP) & (ev["label"] == "tap")
    marks = np.sort(_seconds(ev.loc[tapped, "log_time"]))
    acc = st.streams[ACCEL].sort_values("micros", kind="stable")  # host jitter reorders the rows
    t = _device_time(acc)
    a = acc[[f"acceleration_{i}" for i in range(3)]].to_numpy()
    fs = 1.0 / np.median(np.diff(t))
    taps = impacts(t, a, marks)
    ends = np.append(taps[1:], t[-1]) - TAP_SKIP_S / 2
    rows = []
    for i, (t0, t1) in enumerate(zip(taps + TAP_SKIP_S, ends, strict=True)):
        sel = (t >= t0) & (t < t1)
        f_s, zeta = free_oscillation(t[sel], a[sel], fs)
        rows.append({"session_id": st.session_id, "robot": st.robot.name, "tap": i, "f_s_hz": f_s,
                     "zeta": zeta})  # fmt: skip
    out = pd.DataFrame(rows)
    out.insert(1, "pressure_pa", float(st.parameters["pressure_pa"]))
    return out


def impact_parameters(sessions: list[Path]) -> pd.DataFrame:
    """Per pressure: mean and std over taps of the damped frequency f_s [Hz] and damping ratio ζ."""
    return tap_parameters(pd.concat([impact_taps(s) for s in sessions], ignore_index=True))


def tap_parameters(taps: pd.DataFrame) -> pd.DataFrame:
    """:func:`impact_parameters` of the taps of its sessions (:func:`impact_taps`, concatenated)."""
    out = taps.groupby("pressure_pa").agg(
        f_s_hz=("f_s_hz", "mean"), f_s_std_hz=("f_s_hz", "std"),
        zeta=("zeta", "mean"), zeta_std=("zeta", "std"), taps=("tap", "count"),
    ).reset_index()  # fmt: skip
    out.attrs["sessions"] = sorted(taps["session_id"].unique().tolist())
    return out


def table1_estimates(static_k: pd.DataFrame, impact: pd.DataFrame) -> pd.DataFrame:
    """Seed 001's procedure: I = k/(2π f_n)² at each pressure with both tests, f_n = f_s/sqrt(1−ζ²); one I =
    their mean; k̂ = I (2π f_n)², ĉ = 2 ζ sqrt(k̂ I) at every dynamic-test pressure (``pressure_kpa``, f_s, ζ,
    static k where measured, k̂, ĉ, the taps' spreads and I)."""
    t = impact.merge(static_k[["pressure_pa", "k"]], on="pressure_pa", how="left")
    w_n = 2 * np.pi * t["f_s_hz"] / np.sqrt(1 - t["zeta"] ** 2)
    inertia = float(np.nanmean(t["k"] / w_n**2))
    t["k_hat"] = inertia * w_n**2
    t["c_hat"] = prbm.damping_from_ratio(t["zeta"], t["k_hat"], inertia)
    t["inertia_kgm2"] = inertia
    t.insert(0, "pressure_kpa", t.pop("pressure_pa") / 1e3)
    return t[
        ["pressure_kpa", "f_s_hz", "zeta", "k", "k_hat", "c_hat", "f_s_std_hz", "zeta_std", "inertia_kgm2"]
    ]
