"""Seed 001's experiments in real time on the rig, through the devices' wires (Aurora serial, the CAN bus with
the tip IMU at 1 kHz):

- ``vslab run popup_static|popup_impact --rig`` load and tap link 2, and the pipeline reads the sessions
  exactly as simulated ones: Table 1 comes back out as the twin's configured link within the bounds
  tests/test_popup_analysis.py holds the simulated sessions to (f_s 1 %, ζ 5 %, k̂ 5 %, ĉ 15 %);
- ``vslab run popup_deploy --rig`` inflates link 1, goes on to link 2 once link 1's transducer reads its set
  point, and the session's own pressure checks pass;
- ``vslab run popup_reach --rig`` follows the velocity law of Figs. 12–13 and misses the target by the links'
  bending, as the analysis predicts.

The rig starts as each plan begins (its bench set up by the operator); each ``settle`` waits, in real time,
until the arm is still and every regulated link at its pressure."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pandas as pd
import pytest
from machine_stalls import STALL_S, STEAL_SHARE, StallWatches, StealWatch
from scipy.spatial.transform import Rotation

from acquisition.plans.popup_experiments import pressure_checks, verify_pressure_checks
from acquisition.recorder.daemon import MAX_LAG_S
from acquisition.recorder.sessions import SessionStore, session_info
from acquisition.schemas import topics as T
from acquisition.schemas.events import EventKind
from acquisition.schemas.fast_read import read_events, read_fixed_topics
from acquisition.schemas.session_card import readable_parts
from analysis import popup_tests as pt
from analysis.popup_reach import reach
from models import prbm
from models.robot import load_robot
from models.statics import static_deflection
from pipeline import link_tests as lt
from pipeline.build import build
from pipeline.lab import Lab
from pipeline.session_index import sessions_of
from twin.runner import simulate_experiment
from twin.streams import tracker_spec

# Each test judges recordings made in real time, one rig at a time: they run alone, after the
# other tests' workers (`make test`), like every test that judges a real-time recording. Beside another worker
# on a slow 2-core machine all four failed in one run, the CAN host starved ("host not reading").
pytestmark = pytest.mark.real_time

INERTIA = 0.0358  # the twin's link 2 about its virtual hinge (tests/test_popup_analysis.py)
PRESSURES_KPA = (10, 50)
IMPACT = ["taps=2", "record_s=1.2", "settle_s=1.0"]
# one repetition of 5 loads up to 0.45 M_c, all below M_w (the loading branch below M_w is what k reads),
# settled 1 s and held 1 s: over seeds 1-10 of the simulated test the mean static k of the two pressures
# came within 1.9 % of the configured link, each pressure's within 3.2 % (k̂ rests on that mean), in 19 s of
# real time a pressure; the default 7 loads up to 0.8 M_c settled 1.2 s and held 2 s (seeds 1-6): 2.9 % and
# 5.1 %, in 42.6 s
STATIC = ["repetitions=1", "pressure_settle_s=1.0", "settle_s=1.0", "hold_s=1.0", "load_steps=4",
          "max_collapse_fraction=0.45"]  # fmt: skip


# the module's real-time sessions: name → (experiment, plan number, --set settings)
SESSIONS = {
    **{f"impact-{kpa}": ("popup_impact", i, IMPACT) for i, kpa in enumerate(PRESSURES_KPA)},
    **{f"static-{kpa}": ("popup_static", i, STATIC) for i, kpa in enumerate(PRESSURES_KPA)},
    "deploy": ("popup_deploy", 0, []),
    "reach": ("popup_reach", 0, []),
}


STOLEN_MS: dict[str, float] = {}  # per session: CPU time the hypervisor took while it was recorded
BURST_MS: dict[str, float] = {}  # per session: the most it took within any STALL_WINDOW_S meanwhile
STOPPED_MS: dict[str, float | None] = {}  # per session: a CPU's longest stop (None: watches not real-time)
STALL_WINDOW_S = 0.5


# one rig at a time: two at once (each emulating the CAN bus and its 1 kHz IMU) starved the host's CAN
# reading on a slow 2-core machine, alone in the real-time run (a drive's heartbeat missed for 0.33 s); the
# static tests likewise: side by side with a busy process on each core, two rigs read k̂ 6 % low
@pytest.fixture(scope="module")
def recorded(tmp_path_factory):
    """``recorded(name)``: the session of :data:`SESSIONS` run with ``vslab run … --rig`` into the module's
    lab (each recorded once, when a test first needs it, on a rig of its own); ``recorded.lab`` is the lab."""
    lab = tmp_path_factory.mktemp("popup-rt") / "lab"
    done: dict[str, object] = {}

    def session(name: str):
        if name not in done:
            run, watches = _start(lab, name)
            try:
                done[name] = _finish(lab, name, run, *watches)
            except BaseException as failed:  # each test that needs it is told the same (its folder is kept)
                done[name] = failed
                raise
            finally:  # it failed: the recording does not outlive the test
                if run.poll() is None:
                    run.kill()
                    run.wait()
        if isinstance(done[name], BaseException):
            raise done[name]
        return done[name]

    session.lab = lab
    return session


def _start(lab, session: str) -> tuple[subprocess.Popen, tuple[StealWatch, StallWatches]]:
    experiment, plan, settings = SESSIONS[session]
    cli = [sys.executable, "-m", "vslab.cli", "--lab", str(lab), "--quiet"]
    tests = ("popup_static", "popup_impact")
    pressures = [f"pressures_kpa=[{', '.join(map(str, PRESSURES_KPA))}]"] if experiment in tests else []
    sets = [arg for s in (*pressures, *settings) for arg in ("--set", s)]
    command = [*cli, "run", experiment, "--plan", str(plan), *sets, "--rig", "--session", session]
    watches = StealWatch().start(), StallWatches()
    return subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True), watches


def _finish(lab, session: str, run: subprocess.Popen, watch: StealWatch, stalls: StallWatches):
    try:
        out, err = run.communicate(timeout=300)
    finally:
        watch.stop()
        longest = max(stalls.longest_ms().values()) if stalls.real_time else None
        stalls.close()
    stolen, burst = watch.total_ms, watch.burst_ms(STALL_WINDOW_S)
    said = (f"the hypervisor took {stolen:.0f} ms of CPU ({watch.share:.1%} of the CPUs), {burst:.0f} within "
            f"{STALL_WINDOW_S} s") + (
        f"; the machine ran nothing for {longest:.0f} ms at once" if longest is not None else "")  # fmt: skip
    # judged as RealTimeCheck judges a recording: a CPU stopped, or a tenth of the machine taken (the steal's
    # bursts are not: 50 ms within 0.5 s came with no CPU stopped, and hid a session's safe stop)
    stopped = longest >= STALL_S * 1e3 if longest is not None else burst >= MAX_LAG_S * 1e3
    if run.returncode != 0 and (stopped or watch.share >= STEAL_SHARE):
        last = (out + err).strip().splitlines() or [""]
        pytest.skip(f"session {session} stopped on a machine that stopped during it ({said}): {last[-1]}")
    assert run.returncode == 0, f"{out[-2000:]}{err[-2000:]}\n(meanwhile {said})"
    assert session_info(lab / "sessions" / session).status == "complete"
    STOLEN_MS[session] = watch.total_ms  # said with a failure of the datasets test
    BURST_MS[session] = watch.burst_ms(STALL_WINDOW_S)
    STOPPED_MS[session] = longest
    return lab / "sessions" / session


def _configured_link2(pressure_kpa) -> tuple[np.ndarray, np.ndarray]:
    """(k, c) of the twin's link 2 at these pressures."""
    link = load_robot("popup").link_table("link2")
    p = np.asarray(pressure_kpa, float) * 1e3
    return (np.interp(p, link.pressure_pa, link.stiffness_nm_per_rad),
            np.interp(p, link.pressure_pa, link.damping_nms_per_rad))  # fmt: skip


@pytest.mark.slow
def test_real_time_taps_ring_at_the_link_s_frequency_and_damping(recorded):
    """The impact tests alone: each pressure's taps give the twin's f_s within 1 % and ζ within 5 %."""
    taps = lt.impact_parameters([recorded(f"impact-{kpa}") for kpa in PRESSURES_KPA])
    assert (taps["pressure_pa"] / 1e3).tolist() == list(PRESSURES_KPA) and (taps["taps"] == 2).all()
    k, c = _configured_link2(taps["pressure_pa"] / 1e3)
    np.testing.assert_allclose(taps["f_s_hz"], prbm.damped_frequency_hz(k, c, INERTIA), rtol=0.01)
    np.testing.assert_allclose(taps["zeta"], prbm.damping_ratio(k, c, INERTIA), rtol=0.05)


@pytest.mark.slow
def test_table1_from_real_time_link_tests(recorded):
    """The static tests with the taps (recorded for the test above): Table 1 as the twin's link 2."""
    impact = [recorded(f"impact-{kpa}") for kpa in PRESSURES_KPA]
    static = [recorded(f"static-{kpa}") for kpa in PRESSURES_KPA]
    table = pt.table1(lt.static_stiffness(lt.link_static_curves(static)), lt.impact_parameters(impact))
    assert table["pressure_kpa"].tolist() == list(PRESSURES_KPA)
    k, c = _configured_link2(table["pressure_kpa"])
    np.testing.assert_allclose(table["f_s_hz"], prbm.damped_frequency_hz(k, c, INERTIA), rtol=0.01)
    np.testing.assert_allclose(table["zeta"], prbm.damping_ratio(k, c, INERTIA), rtol=0.05)
    np.testing.assert_allclose(table["k_hat"], k, rtol=0.05)
    np.testing.assert_allclose(table["c_hat"], c, rtol=0.15)


@pytest.mark.slow
def test_a_deployment_in_real_time_checks_link_1_before_link_2(recorded):
    session = recorded("deploy")
    (part,) = readable_parts(session)
    pressure = read_fixed_topics(part)[T.PRESSURE]
    events = [(t / 1e9, e) for t, e in read_events(part)]
    assert EventKind.SAFETY_STOP not in [e.kind for _, e in events]
    checks = pressure_checks(events)
    t, p = pressure.log_time.astype(np.int64) / 1e9, pressure.rows["pressure"]
    results = verify_pressure_checks(checks, t, p)
    assert [r[0] for r in results] == [0, 1] and all(r[3] for r in results), results
    inflate_link2 = next(at for at, e in events if e.label == "inflate" and e.index == 1)
    assert checks[0][0] <= inflate_link2  # link 2's valve opened only after link 1's check
    assert p[t < inflate_link2, 1].max() < 1e3  # link 2 stayed deflated until then
    assert p[t < checks[0][0] - 1.0, 0].min() < 1e3  # link 1 started deflated (the bench set up as the plan)


@pytest.mark.slow
def test_the_velocity_law_reach_in_real_time_misses_by_the_links_bending(recorded, popup):
    """``vslab run popup_reach --rig``: the joints follow eq. (3)'s path planned on the rigid model with 2 kg
    at 60 kPa; at the settled start and target the tracked tip (in the base frame by the twin's tracker
    placement) is where the PRBM puts it, and away from the rigid model's tip by what
    ``analysis.popup_reach`` predicts for Figs. 12–13."""
    session = recorded("reach")
    (part,) = readable_parts(session)
    data = read_fixed_topics(part)
    events = read_events(part)
    assert EventKind.SAFETY_STOP not in [e.kind for _, e in events]
    to_base = np.linalg.inv(tracker_spec(popup).base_to_tracker)
    tracker, joints = data[T.TRACKER], data[T.JOINT_STATE]
    tip_base = tracker.rows["position"] @ to_base[:3, :3].T + to_base[:3, 3]
    predicted = reach(popup, dt=0.01)  # the experiment's defaults: seed 001's task
    chain, pressure = popup.chain(), np.full(2, 60e3)
    holds = [(t, e) for t, e in events if e.kind == EventKind.SETTLED and e.index >= 0]
    assert [e.index for _, e in holds] == [0, 1]
    for (t, e), planned in zip(holds, (predicted.q[0], predicted.q[-1]), strict=True):
        window = slice(*np.searchsorted(joints.log_time, [t, t + e.value * 1e9]))
        q = joints.rows["position"][window].mean(axis=0)
        np.testing.assert_allclose(q, planned, atol=0.015)  # reached, within the drives' droop under 2 kg
        window = slice(*np.searchsorted(tracker.log_time, [t, t + e.value * 1e9]))
        tip = np.nanmean(tip_base[window], axis=0)
        soft = chain.position(q, static_deflection(popup, q, pressure, 2.0)[0])
        assert np.linalg.norm(tip - soft) < 3e-3, "the tracked tip is where the PRBM puts it"
        expected = predicted.difference_mm[0 if e.index == 0 else -1]
        assert 1e3 * np.linalg.norm(tip - chain.position(q)) == pytest.approx(expected, abs=3.0)


@pytest.mark.slow
def test_real_time_popup_sessions_build_into_datasets(recorded, popup):
    """The pipeline builds the real-time deployment, reach and impact sessions as it builds simulated ones:
    the tracker registered on a survey of the same setup (its static points span the workspace; a reach
    moves the tip along a line, a link test not at all), D with the drives' torques, the reach's path."""
    sessions = [recorded(name) for name in ("deploy", "reach", "impact-10")]
    lab = recorded.lab
    simulate_experiment("popup_survey", SessionStore(lab / "sessions"), seed=1)
    survey = build(sessions_of(SessionStore(lab / "sessions"), "popup_survey"), Lab(lab), "popup_survey")
    fitted = np.array(
        json.loads((survey.path / "card.json").read_text())["registration"]["popup"]["base_to_tracker"]
    )
    truth = tracker_spec(popup).base_to_tracker
    assert np.degrees(Rotation.from_matrix(fitted[:3, :3] @ truth[:3, :3].T).magnitude()) < 0.05
    assert np.linalg.norm(fitted[:3, 3] - truth[:3, 3]) < 0.5e-3
    borrowed = {"registration": {"from_dataset": f"popup_survey@{survey.version}"}}
    built = {s.name: build([s], Lab(lab), f"rt-{s.name}", borrowed) for s in sessions}
    deploy = pd.read_parquet(built["deploy"].path / "data.parquet")
    assert len(deploy) == 1 and deploy["p_0"].iloc[0] == pytest.approx(50e3, rel=0.03)  # the deployed arm
    taps = pd.read_parquet(built["impact-10"].path / "trajectories.parquet")
    assert sorted(taps["repetition"].unique()) == [0, 1]
    reach_d = pd.read_parquet(built["reach"].path / "data.parquet")
    if reach_d["point"].tolist() != [0, 1]:
        # CI once found none: the runner called the arm settled when its joints were, while link 2 still
        # bounced ±4 mm under the 2 kg (the runner now waits for the tracked tip too)
        card = json.loads((built["reach"].path / "card.json").read_text())["sessions"]["reach"]
        pytest.fail(f"settled windows rejected: {card['removed']}; ms stolen while recording: {STOLEN_MS}, "
                    f"the most within {STALL_WINDOW_S} s: {BURST_MS}")  # fmt: skip
    assert reach_d["payload_kg"].tolist() == [2.0, 2.0]
    q = reach_d[[f"q_{j}" for j in range(3)]].to_numpy()
    x = reach_d[[f"x_{k}" for k in range(3)]].to_numpy()
    soft = popup.chain().position(q, static_deflection(popup, q, np.full((2, 2), 60e3), 2.0)[0])
    assert np.linalg.norm(x - soft, axis=1).max() < 3e-3  # registered by the survey, where the PRBM says
    assert np.isfinite(reach_d[[f"tau_{k}" for k in range(3)]].to_numpy()).all()  # the drives' torques
    path = pd.read_parquet(built["reach"].path / "trajectories.parquet")
    assert len(path) > 30 * 9 and (path["repetition"] == 0).all()  # ≈ 11 s at the tracker's 40 Hz
    tip = path[[f"x_{k}" for k in range(3)]].to_numpy()
    # the path runs from the start hold to the target hold (how far the arm still lags at the path's end
    # depends on how late the busy host sent the last set-points: 30 mm under bench/load.py; 163 mm in a CI
    # run whose hypervisor took the CPUs: checked only when it did not stall it, taking MAX_LAG_S within any
    # STALL_WINDOW_S; 60-70 ms spread over the ~15 s of the command beside another test worker is no stall)
    # A CPU's stall watch is the witness where it runs at real-time priority (the steal counts the machine's
    # own wake-ups too: tests/machine_stalls.py), the steal where it does not.
    stopped = STOPPED_MS["reach"]
    if stopped is not None and stopped >= STALL_S * 1e3:
        pytest.skip(f"a CPU ran nothing for {stopped:.0f} ms at once while the reach was recorded")
    if stopped is None and BURST_MS["reach"] >= MAX_LAG_S * 1e3:
        pytest.skip(f"the hypervisor took {BURST_MS['reach']:.0f} ms of the CPUs within {STALL_WINDOW_S} s "
                    f"while the reach was recorded ({STOLEN_MS['reach']:.0f} ms in all)")  # fmt: skip
    missed = np.linalg.norm(tip[-1] - x[1])
    assert missed < 0.1 * np.linalg.norm(tip[0] - x[1]), (
        f"{missed * 1e3:.0f} mm from the target at the path's end; while recorded: a CPU's longest stop "
        f"{stopped} ms, steal {STOLEN_MS['reach']:.0f} ms ({BURST_MS['reach']:.0f} within {STALL_WINDOW_S} s)"
    )
