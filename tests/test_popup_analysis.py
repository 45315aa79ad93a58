"""Seed 001's Table 1 and Figure 7 from twin link tests (analysis.popup_tests): the twin's configured link-2
stiffness, damping and damped frequency come back out of the static and impact sessions, run on the twin as
configured (wrinkling and hysteresis included), by the paper's procedure."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest
from conftest import perturbed_popup
from scipy import signal

from acquisition.recorder.sessions import SessionStore
from analysis import popup_tests as pt
from models import prbm
from models.robot import load_robot
from pipeline import link_tests as lt
from twin.runner import simulate_experiment

SEED = 7
INERTIA = (
    0.0358  # the twin's link 2 about its virtual hinge: 0.30 kg · 0.295² + 0.0097 (configs/robots/popup.yaml)
)
IMPACT = {"pressures_kpa": [10, 50, 90], "taps": 2, "record_s": 1.2, "settle_s": 1.0}
# hold_s: the static k at 10 kPa rests on 3 loads below M_w, each the mean of the tracker over its hold; with
# 0.8 s holds the inertia I = k / w_n² spread 2.7 % (rms) over seeds 1-8 (worst 5.1 %, against k-hat's 5 %),
# with 2 s holds 1.3 % (worst 2.5 %)
STATIC = {"pressures_kpa": [10, 50], "repetitions": 2, "pressure_settle_s": 1.0, "settle_s": 1.2,
          "hold_s": 2.0}  # fmt: skip


@pytest.fixture(scope="module")
def link2():
    return load_robot("popup").link_table("link2")


def _configured(table, kpa):
    p = np.asarray(kpa, float) * 1e3
    return (np.interp(p, table.pressure_pa, table.stiffness_nm_per_rad),
            np.interp(p, table.pressure_pa, table.damping_nms_per_rad))  # fmt: skip


@pytest.fixture(scope="module")
def root(tmp_path_factory):
    return tmp_path_factory.mktemp("popup_tests")


@pytest.fixture(scope="module")
def impact_dir(root):
    simulate_experiment("popup_impact", SessionStore(root / "impact"), seed=SEED, overrides=IMPACT)
    return root / "impact"


@pytest.fixture(scope="module")
def static_dir(root):
    simulate_experiment("popup_static", SessionStore(root / "static"), seed=SEED, overrides=STATIC)
    return root / "static"


def _sessions(directory):
    return sorted(p for p in directory.iterdir() if p.is_dir())


@pytest.fixture(scope="module")
def curves(static_dir):
    return lt.link_static_curves(_sessions(static_dir))


@pytest.fixture(scope="module")
def table(impact_dir, curves):
    static_k = lt.static_stiffness(curves)
    return pt.table1(static_k, lt.impact_parameters(_sessions(impact_dir)))


@pytest.mark.slow
def test_table1_recovers_the_twins_link2(table, link2):
    kpa = table["pressure_kpa"].to_numpy()
    assert kpa.tolist() == IMPACT["pressures_kpa"]
    k, c = _configured(link2, kpa)
    f_s = prbm.damped_frequency_hz(k, c, INERTIA)
    np.testing.assert_allclose(table["f_s_hz"], f_s, rtol=0.01)
    np.testing.assert_allclose(table["zeta"], prbm.damping_ratio(k, c, INERTIA), rtol=0.05)
    np.testing.assert_allclose(table["k_hat"], k, rtol=0.05)
    np.testing.assert_allclose(table["c_hat"], c, rtol=0.15)
    assert table["inertia_kgm2"].iloc[0] == pytest.approx(INERTIA, rel=0.05)
    static = table.dropna(subset=["k"])
    assert static["pressure_kpa"].tolist() == STATIC["pressures_kpa"]
    np.testing.assert_allclose(static["k"], _configured(link2, static["pressure_kpa"])[0], rtol=0.05)
    assert table["paper_k_hat"].tolist() == [321, 382, 405]
    md = pt.table1_markdown(table)
    assert md.count("\n| ") == len(table) and "N/A" in md
    side = pt.table1_side_by_side(table)
    assert side.loc["90", "k (N·m/rad)"] == "N/A / N/A"
    assert side.loc["10", "k̂ (N·m/rad)"] == f"{table['k_hat'].iloc[0]:.0f} / 321"


# the perturbed twins of issue 19: link 2's stiffness and damping each ×0.5, ×0.7, ×1.3, ×1.5, and the two
# corners (softest and most damped: ζ up to 0.17 at 10 kPa; stiffest and least damped: ζ down to 0.02)
PERTURBED = [(fk, 1.0) for fk in (0.5, 0.7, 1.3, 1.5)] + [(1.0, fc) for fc in (0.5, 0.7, 1.3, 1.5)]
PERTURBED += [(0.5, 1.5), (1.5, 0.5)]


@pytest.mark.slow
@pytest.mark.parametrize(("k_factor", "c_factor"), PERTURBED)
def test_table1_recovers_perturbed_twins(tmp_path, k_factor, c_factor):
    """Table 1 by the paper's procedure on twins whose link 2 is not the paper's: f_s within 1 %, ζ 5 %,
    k̂ 5 %, ĉ 15 % of what the twin was given, whatever the damping."""
    robot = perturbed_popup(tmp_path / "popup.yaml", k_factor, c_factor)
    simulate_experiment(
        "popup_impact", SessionStore(tmp_path / "impact"), seed=SEED, overrides=IMPACT | {"robot": str(robot)}
    )
    simulate_experiment(
        "popup_static", SessionStore(tmp_path / "static"), seed=SEED, overrides=STATIC | {"robot": str(robot)}
    )
    static_k = lt.static_stiffness(lt.link_static_curves(_sessions(tmp_path / "static")))
    table = pt.table1(static_k, lt.impact_parameters(_sessions(tmp_path / "impact")))
    k, c = _configured(load_robot(robot).link_table("link2"), table["pressure_kpa"].to_numpy())
    np.testing.assert_allclose(table["f_s_hz"], prbm.damped_frequency_hz(k, c, INERTIA), rtol=0.01)
    np.testing.assert_allclose(table["zeta"], prbm.damping_ratio(k, c, INERTIA), rtol=0.05)
    np.testing.assert_allclose(table["k_hat"], k, rtol=0.05)
    np.testing.assert_allclose(table["c_hat"], c, rtol=0.15)


@pytest.mark.parametrize("zeta", [0.01, 0.05, 0.1, 0.15, 0.2])
@pytest.mark.parametrize("f_n", [4.0, 15.0])
def test_free_oscillation_fits_a_damped_acceleration(zeta, f_n):
    """A tip accelerometer's free oscillation (3 axes, gravity, 1 kHz, 0.02 m/s² noise): the fit gives the
    damped frequency within 0.2 % and ζ within 2 % up to ζ = 0.2. The spectrum's peak, the estimate the fit
    replaced, is off by more than 1 % there."""
    rng = np.random.default_rng(int(zeta * 100 + f_n))
    fs, w_n = 1000.0, 2 * np.pi * f_n
    sigma, w_d = zeta * w_n, w_n * np.sqrt(1 - zeta**2)
    t = np.arange(int(fs * 1.2)) / fs
    delta = 0.01 * np.exp(-sigma * t) * np.cos(w_d * t + 0.3)
    accel = -(w_n**2) * delta - 2 * sigma * np.gradient(delta, t)  # δ'' = −ω_n² δ − 2σ δ'
    gravity = np.array([0.0, 0.3, -9.81])
    a = np.outer(accel, [0.8, 0.1, 0.59]) + gravity + rng.normal(0, 0.02, (len(t), 3))
    f_s, z = lt.free_oscillation(t, a, fs)
    assert f_s == pytest.approx(w_d / (2 * np.pi), rel=0.002)
    assert z == pytest.approx(zeta, rel=0.02)
    if zeta == 0.2:
        f, psd = signal.welch(accel, fs=fs, window="boxcar", nperseg=len(t), nfft=lt.NFFT)
        assert abs(f[np.argmax(psd)] / (w_d / (2 * np.pi)) - 1) > 0.01


@pytest.mark.parametrize("late_s", [-0.08, 0.0, 0.055, 0.2])
def test_impacts_are_found_in_the_acceleration_not_at_their_events(late_s):
    """Two taps 1.17 s apart, the events logged ``late_s`` after each impact (a busy host logged them up to
    55 ms late; an operator who presses Enter after tapping, later still): each impact is found at its own
    sample, and the window of the first tap's free oscillation ends before the second impact, so the damped
    frequency and ζ come out as when the events are exact (a 55 ms late event let the second impact into
    the first window: ζ 0.058 came out 0.000)."""
    fs, f_n, zeta = 1000.0, 16.4, 0.058
    w_n = 2 * np.pi * f_n
    sigma, w_d = zeta * w_n, w_n * np.sqrt(1 - zeta**2)
    t = np.arange(int(fs * 4.0)) / fs
    hits = np.array([1.234, 2.404])
    accel = np.zeros_like(t)
    for hit in hits:
        after = t >= hit
        tau = t[after] - hit
        accel[after] += 30.0 * np.exp(-sigma * tau) * np.cos(w_d * tau)
        accel[np.flatnonzero(after)[0]] += 160.0  # the impulse's own sample
    rng = np.random.default_rng(3)
    a = np.outer(accel, [0.8, 0.1, 0.59]) + np.array([0.0, 0.3, -9.81]) + rng.normal(0, 0.02, (len(t), 3))
    found = lt.impacts(t, a, hits + late_s)
    np.testing.assert_allclose(found, hits, atol=0.5 / fs)
    first = (t >= found[0] + lt.TAP_SKIP_S) & (t < found[1] - lt.TAP_SKIP_S / 2)
    f_s, z = lt.free_oscillation(t[first], a[first], fs)
    assert f_s == pytest.approx(w_d / (2 * np.pi), rel=0.002)
    assert z == pytest.approx(zeta, rel=0.02)


def test_static_points_below_wrinkling(curves):
    assert set(curves["branch"]) == {"loading", "unloading"} and (curves["n_runs"] == 2).all()
    assert curves["arm_m"].iloc[0] == pytest.approx(0.590)  # the twin's hinge → tip (paper: l2 = 0.570 m)
    m_w = prbm.wrinkling_moment(curves["pressure_pa"], 0.055)
    np.testing.assert_allclose(curves["wrinkling_moment_nm"], m_w)
    k = lt.static_stiffness(curves)
    # 7 masses up to 0.8 M_c: 3 below M_w at 10 kPa (own weight 0.87 N·m), 4 at 50 kPa, on the loading branch
    assert k["n_points"].tolist() == [3, 4]
    both = lt.static_stiffness(curves, branch=None)
    assert (both["n_points"] == 2 * k["n_points"]).all()


@pytest.fixture(scope="module")
def hysteresis_curves(root):
    """Figure 7's sessions: the configured twin, 3 runs."""
    # the heaviest masses ring at ≈ 3.5 Hz with ζ ≈ 0.015 (c/2I ≈ 0.3 /s): settle as the protocol does
    fig7 = STATIC | {"pressures_kpa": [20, 40], "repetitions": 3, "settle_s": 5.0, "hold_s": 1.0}
    simulate_experiment("popup_static", SessionStore(root / "hysteresis"), seed=SEED, overrides=fig7)
    return lt.link_static_curves(_sessions(root / "hysteresis"))


def _noise_bound(arm_m: float, hold_s: float, runs: int, k: float = 4.0) -> float:
    """k standard errors (rad) of a mean point of the curves from the tracker noise the twin draws.

    A point's δ is (z₀ − z)/arm: z the tracker's mean height over a hold (n = hold_s · frame rate frames, each
    with σ = noise_m, so σ/√n), averaged over the runs; z₀ the session's first hold, one for every run. So
    σ_δ = noise_m / (arm √n) · √(1/runs + 1): 0.25 mm, 40 frames, 0.59 m, 3 runs → 0.077 mrad. With k = 4,
    each of the 26 points stays inside by chance with probability 1 − 6.3e-5 (all 26: 99.8 %)."""
    tracker = load_robot("popup").sensors.tracker
    n = hold_s * tracker.frame_rate_hz
    return k * tracker.noise_m / (arm_m * np.sqrt(n)) * np.sqrt(1.0 / runs + 1.0)


@pytest.mark.slow
def test_static_curves_follow_the_link_model(hysteresis_curves, link2):
    """The mean curves are the quasi-static link model's (elastic below M_w, softening and a hysteresis loop
    above it) over the same load history, averaged over the 3 runs."""
    curves = hysteresis_curves
    own = 0.30 * 9.81 * 0.295  # link 2's own moment about its hinge
    for p, c in curves.groupby("pressure_pa"):
        k = _configured(link2, p / 1e3)[0]
        m_w = prbm.wrinkling_moment(p, 0.055)
        one = c["torque_nm"].to_numpy()  # loading up, unloading down: one repetition
        torque = np.concatenate([[own], np.tile(one, 3)])
        delta = prbm.static_loading_curve(torque, k, 0.00436, 1.8, m_w)[1:]
        model = (delta - delta[0]).reshape(3, -1).mean(axis=0)
        residual = c["delta_rad"].to_numpy() - model
        bound = _noise_bound(c["arm_m"].iloc[0], hold_s=1.0, runs=3)
        # The loop's peak (the heaviest load, on the wrinkled link) is not noise-limited: seeds 0-10 put
        # it 0.19-0.46 mrad above the quasi-static model at 40 kPa (mean 0.28, spread the noise's 0.08), the
        # twin's settling there, which the quasi-static model does not have. It is held one-sided, within
        # half the configured loop (δ_h/2 = 2.2 mrad) above: a top further off would be another loop.
        peak = one == one.max()
        assert np.abs(residual[~peak]).max() <= bound, (p, residual * 1e3, bound * 1e3)
        half_loop = 0.00436 / 2  # δ_h / 2 (configs/robots/popup.yaml)
        assert -bound <= residual[peak].min() <= residual[peak].max() <= bound + half_loop, p
        top = c["torque_nm"] > m_w
        gap = np.interp(
            one[top][0], one[one.argmax() :][::-1], c["delta_rad"].to_numpy()[one.argmax() :][::-1]
        )
        assert gap - c["delta_rad"].to_numpy()[top][0] > 1e-3  # the loop opens above M_w


def test_figure7_plots_the_curves(hysteresis_curves, tmp_path):
    curves = hysteresis_curves
    data = pt.figure7(curves, tmp_path)
    png = tmp_path / "fig7_popup_hysteresis.png"
    assert png.stat().st_size > 10_000 and (tmp_path / "fig7_popup_hysteresis.pdf").stat().st_size > 0
    assert set(data) == {(kpa, b) for kpa in (20.0, 40.0) for b in ("loading", "unloading")}
    for (kpa, branch), line in data.items():
        c = curves[curves["pressure_pa"] == kpa * 1e3]
        load, part = c[c["branch"] == "loading"], c[c["branch"] == branch]
        if branch == "unloading":  # drawn from the top of the loading branch
            part = pd.concat([load.iloc[-1:], part])
        np.testing.assert_allclose(line["x_deg"], np.degrees(part["delta_rad"]))
        np.testing.assert_allclose(line["y_nm"], part["torque_nm"])
        np.testing.assert_allclose(line["xerr_deg"], np.degrees(part["delta_std_rad"]))
    loop = data[(20.0, "unloading")]["x_deg"][1:][::-1] - data[(20.0, "loading")]["x_deg"][:-1]
    assert 0.05 < np.abs(loop).max() < 1.0  # a hysteresis loop of a fraction of a degree (paper: ≈ 0.5°)
