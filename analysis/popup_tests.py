"""Seed 001's link tests on the POPUP arm: Table 1 (static k, damped frequency, damping) and Figure 7 (static
loading/unloading characteristic) from ``popup_static`` / ``popup_impact`` sessions.

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

from analysis.figure_files import save_figure
from models import prbm
from models.robot import RobotDescription
from pipeline.ingest import ingest_session
from pipeline.tables import EventKind

G = 9.81
PAPER_L1_M, PAPER_L2_M = 0.030, 0.570  # seed 001 Sec. 4: PRBM body lengths of the 600 mm link
TRACKER, ACCEL = "/tracker/pose", "/imu/accel"
BRANCHES = ("loading", "unloading")
TAP_SKIP_S = 0.02  # after a tap: skip the hammer contact before the free oscillation
PEAK_FLOOR = 0.05  # the free oscillation is fitted from its largest peak down to 5 % of it (above the noise)
NFFT = 2**17  # zero padding of the PSD (the fit's starting frequency): 1 kHz / 2^17 ≈ 0.008 Hz bins

# Seed 001, Table 1 ("Test results: estimated parameters"), transcribed from the paper text (seeds/001_*.txt,
# Sec. "Experiments"); k is N/A (no static test) above 50 kPa.
PAPER_TABLE1 = pd.DataFrame(
    {
        "pressure_kpa": [10, 20, 30, 40, 50, 60, 70, 80, 90],
        "f_s_hz": [15.04, 15.63, 15.94, 16.17, 16.44, 16.56, 16.65, 16.83, 16.93],
        "c_hat": [0.557, 0.547, 0.463, 0.450, 0.433, 0.429, 0.412, 0.407, 0.406],
        "k": [296, 346, 348, 389, 407, np.nan, np.nan, np.nan, np.nan],
        "k_hat": [321, 347, 360, 370, 382, 388, 392, 401, 405],
    }
)


def _seconds(log_time) -> np.ndarray:
    return np.asarray(log_time, np.int64) * 1e-9


def link_geometry(robot: RobotDescription, link: str = "link2") -> tuple[float, float, float]:
    """(arm m, own moment N·m, radius m) of ``link``: its last virtual joint's D-H a_m, the moment of the
    masses on that joint's frame about the hinge, and the link radius."""
    spec = next(lk for lk in robot.links if lk.name == link)
    hinge = spec.virtual_joints[-1]
    arm = next(r.a_m for r in robot.kinematics.rows if r.joint == hinge)
    own = sum(m.mass_kg * G * (arm + m.position_m[0]) for m in robot.masses if m.frame == hinge)
    return float(arm), float(own), float(spec.radius_m)


def _hold_means(t: np.ndarray, x: np.ndarray, t0: np.ndarray, t1: np.ndarray) -> np.ndarray:
    """Mean of x over each window [t0, t1) (t sorted), vectorised with cumulative sums."""
    csum = np.concatenate([[0.0], np.cumsum(x)])
    i0, i1 = np.searchsorted(t, t0), np.searchsorted(t, t1)
    return (csum[i1] - csum[i0]) / np.maximum(i1 - i0, 1)


def static_holds(directory: Path, link: str = "link2", arm_m: float | None = None) -> pd.DataFrame:
    """One row per SETTLED hold of a popup_static session: rep, branch, load, tip displacement, τ, δ."""
    st = ingest_session(directory)
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


def link_static_curves(sessions: list[Path], link: str = "link2", arm_m: float | None = None) -> pd.DataFrame:
    """Mean (and std over the repetitions) static characteristic per pressure, branch and load: τ, δ, v.

    Rows are in test order (loading up, unloading down); ``attrs['sessions']`` names the sessions used."""
    holds = pd.concat([static_holds(s, link, arm_m) for s in sessions], ignore_index=True)
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
    st = ingest_session(directory)
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
        rows.append({"session_id": st.session_id, "tap": i, "f_s_hz": f_s, "zeta": zeta})
    out = pd.DataFrame(rows)
    out.insert(1, "pressure_pa", float(st.parameters["pressure_pa"]))
    return out


def impact_parameters(sessions: list[Path]) -> pd.DataFrame:
    """Per pressure: mean and std over taps of the damped frequency f_s [Hz] and damping ratio ζ."""
    taps = pd.concat([impact_taps(s) for s in sessions], ignore_index=True)
    out = taps.groupby("pressure_pa").agg(
        f_s_hz=("f_s_hz", "mean"), f_s_std_hz=("f_s_hz", "std"),
        zeta=("zeta", "mean"), zeta_std=("zeta", "std"), taps=("tap", "count"),
    ).reset_index()  # fmt: skip
    out.attrs["sessions"] = sorted(taps["session_id"].unique().tolist())
    return out


def table1(static_k: pd.DataFrame, impact: pd.DataFrame) -> pd.DataFrame:
    """Seed 001's procedure: I = k/(2π f_n)² at each pressure with both tests, f_n = f_s/sqrt(1−ζ²); one I =
    their mean; k̂ = I (2π f_n)², ĉ = 2 ζ sqrt(k̂ I) at every dynamic-test pressure. Paper values alongside."""
    t = impact.merge(static_k[["pressure_pa", "k"]], on="pressure_pa", how="left")
    w_n = 2 * np.pi * t["f_s_hz"] / np.sqrt(1 - t["zeta"] ** 2)
    inertia = float(np.nanmean(t["k"] / w_n**2))
    t["k_hat"] = inertia * w_n**2
    t["c_hat"] = prbm.damping_from_ratio(t["zeta"], t["k_hat"], inertia)
    t["inertia_kgm2"] = inertia
    t.insert(0, "pressure_kpa", t.pop("pressure_pa") / 1e3)
    paper = PAPER_TABLE1.rename(
        columns={c: f"paper_{c}" for c in PAPER_TABLE1.columns if c != "pressure_kpa"}
    )
    cols = ["pressure_kpa", "f_s_hz", "zeta", "k", "k_hat", "c_hat", "f_s_std_hz", "zeta_std", "inertia_kgm2"]
    return t[cols].merge(paper, on="pressure_kpa", how="left")


def table1_side_by_side(table: pd.DataFrame) -> pd.DataFrame:
    """Table 1 as text cells "ours / paper's" for f_s, k, k̂, ĉ (N/A where a test has no value), our ζ,
    indexed by pressure (kPa)."""

    def pair(a, b, fmt):
        return " / ".join("N/A" if pd.isna(v) else format(v, fmt) for v in (a, b))

    rows = {
        f"{r.pressure_kpa:g}": {
            "f_s (Hz)": pair(r.f_s_hz, r.paper_f_s_hz, ".2f"),
            "ζ": f"{r.zeta:.4f}",
            "k (N·m/rad)": pair(r.k, r.paper_k, ".0f"),
            "k̂ (N·m/rad)": pair(r.k_hat, r.paper_k_hat, ".0f"),
            "ĉ (N·m·s/rad)": pair(r.c_hat, r.paper_c_hat, ".3f"),
        }
        for r in table.itertuples()
    }
    return pd.DataFrame.from_dict(rows, orient="index").rename_axis("p (kPa)")


def paper_zeta(table: pd.DataFrame) -> pd.Series:
    """The damping ratio ζ the paper's Table 1 implies (it lists f_s, ĉ and k̂, not ζ): with ĉ = 2ζ√(k̂I),
    k̂ = I ω_n² and ω_n = 2π f_s / √(1 − ζ²), ζ√(1 − ζ²) = a := π ĉ f_s / k̂, so ζ² = (1 − √(1 − 4a²)) / 2."""
    a = np.pi * table["paper_c_hat"] * table["paper_f_s_hz"] / table["paper_k_hat"]
    return np.sqrt((1 - np.sqrt(1 - 4 * a**2)) / 2)


# The report's Table 1: (header, our column, the paper's column, format spec), columns of :func:`table1`.
TABLE1_COLUMNS = [
    ("f_s (Hz)", "f_s_hz", "paper_f_s_hz", ".2f"),
    ("ζ", "zeta", "paper_zeta", ".3f"),
    ("k (N·m/rad)", "k", "paper_k", ".0f"),
    ("k̂ (N·m/rad)", "k_hat", "paper_k_hat", ".0f"),
    ("ĉ (N·m·s/rad)", "c_hat", "paper_c_hat", ".3f"),
]


def table1_report(table: pd.DataFrame) -> pd.DataFrame:
    """Table 1 for the report: per pressure (kPa), each parameter ours and the paper's side by side (the
    paper's "name, paper (unit)" column beside ours; NaN where a test has no value, e.g. k above 50 kPa),
    numeric, with each column's format in ``attrs["formats"]``."""
    table = table.assign(paper_zeta=paper_zeta(table))
    out, formats = pd.DataFrame(index=pd.Index(table["pressure_kpa"].to_numpy(), name="p (kPa)")), {}
    for title, ours, paper, spec in TABLE1_COLUMNS:
        name, unit = title.removesuffix(")").rsplit(" (", 1) if "(" in title else (title, "")
        paper_title = f"{name}, paper" + (f" ({unit})" if unit else "")
        out[title], out[paper_title] = table[ours].to_numpy(), table[paper].to_numpy()
        formats |= {title: spec, paper_title: spec}
    out.attrs["formats"] = formats | {"p (kPa)": ".0f"}
    return out


def table1_markdown(table: pd.DataFrame) -> str:
    """Table 1 as a Markdown table: ours / the paper's for f_s, k, k̂, ĉ, and our ζ."""
    side = table1_side_by_side(table)
    header = [side.index.name, *side.columns]
    lines = ["| " + " | ".join(header) + " |", "|---" * len(header) + "|"]
    lines += ["| " + " | ".join([p, *row]) + " |" for p, row in zip(side.index, side.to_numpy(), strict=True)]
    return "\n".join(lines) + "\n\nEach cell: this work / seed 001 Table 1.\n"


def figure7(curves: pd.DataFrame, out_dir: Path) -> dict:
    """Figure 7: torque [N·m] against angular deflection [deg] per pressure, loading solid, unloading dashed
    (drawn from the loading branch's top point), mean of the runs with ±1 std error bars in δ, M_w(p) dotted
    (the end of the linear range). Writes
    ``fig7_popup_hysteresis.{pdf,png}`` (+ ``.json`` with the sessions); returns the plotted arrays:
    ``{(pressure_kpa, branch): {"x_deg", "xerr_deg", "y_nm"}}``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    fig, ax = plt.subplots(figsize=(7.2, 5.2), layout="constrained")
    colours = plt.get_cmap("viridis")(np.linspace(0.0, 0.85, curves["pressure_pa"].nunique()))
    data: dict = {}
    for colour, (p, c) in zip(colours, curves.groupby("pressure_pa"), strict=True):
        load, unload = c[c["branch"] == "loading"], c[c["branch"] == "unloading"]
        for branch, part, style in (
            ("loading", load, "-"),
            ("unloading", pd.concat([load.iloc[-1:], unload]), "--"),
        ):
            x, xerr = np.degrees(part["delta_rad"].to_numpy()), np.degrees(part["delta_std_rad"].to_numpy())
            y = part["torque_nm"].to_numpy()
            label = f"{p / 1e3:g} kPa" if branch == "loading" else None
            ax.errorbar(x, y, xerr=np.nan_to_num(xerr), color=colour, ls=style, marker="o", ms=3, capsize=2,
                        label=label)  # fmt: skip
            data[(p / 1e3, branch)] = {"x_deg": x, "xerr_deg": xerr, "y_nm": y}
        x_all = np.degrees(c["delta_rad"].to_numpy())
        ax.hlines(c["wrinkling_moment_nm"].iloc[0], x_all.min(), x_all.max(), color=colour, ls=":", lw=1.0)
    ax.plot([], [], "k-", label="loading")
    ax.plot([], [], "k--", label="unloading")
    ax.plot([], [], "k:", lw=0.8, label="wrinkling moment $M_w(p)$")
    ax.set_xlabel("angular deflection δ (deg)")
    ax.set_ylabel("torque τ (N·m)")
    ax.set_title("Link 2 static characteristic (mean of runs, ±1 std)", fontsize=10)
    ax.grid(alpha=0.3, axis="x")
    ax.legend(fontsize=8, loc="upper left")
    save_figure(fig, out_dir, "fig7_popup_hysteresis", {"sessions": curves.attrs.get("sessions", [])},
                arm_m=float(curves["arm_m"].iloc[0]), x="delta (deg)", y="torque (N m)")  # fmt: skip
    return data
