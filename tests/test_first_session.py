"""The tutorial "Your first session on the robot" (docs/tutorials/first-session.md), step by step, on `vslab
rig --factory`: devices as they come out of the box (servos all ID 1 at 57,600 baud with Return Delay Time
250, adapters at a 16 ms latency timer).

The lab's description here is vsl's with what a lab writes for its bus: Return Delay Time 0 and the adapter's
latency timer set to 1 ms, and a servo rate the link carries with room to spare on a busy computer
(bus_budget: 588 Sync Reads/s at 1 Mbaud, return delay 0, latency timer 1 ms; 200 asked).
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest
from typer.testing import CliRunner

from acquisition.devices.bus_budget import SerialLink, servo_ceiling_hz
from twin.ptyhost import wait_for_ports
from vslab.cli import app

LAB_ROBOT = """\
extends: vsl
devices:
  servo_bus:
    rate_hz: 200
    return_delay_s: 0.0
    host_link: {latency_timer_s: 0.001}
"""
SERVO_RATE_HZ = 200
RATES_HZ = {"/servo/state": SERVO_RATE_HZ, "/pressure/measured": 250, "/stepper/state": 100,
            "/tracker/pose": 40}  # fmt: skip
runner = CliRunner()


@pytest.fixture(scope="module")
def factory_rig(tmp_path_factory):
    """`vslab rig --factory` of the lab's description, serving for the module: (lab, robot file, run dir)."""
    root = tmp_path_factory.mktemp("first_session")
    robot = root / "lab_vsl.yaml"
    robot.write_text(LAB_ROBOT)
    lab, run_dir = root / "lab", root / "rig"
    proc = subprocess.Popen([sys.executable, "-m", "vslab.cli", "--lab", str(lab), "-q", "rig", "--factory",
                             "--robot", str(robot), "--run-dir", str(run_dir)])  # fmt: skip
    try:
        wait_for_ports(run_dir, timeout_s=60)
        yield lab, robot, run_dir
    finally:
        proc.terminate()
        try:
            proc.wait(timeout=10)
        finally:
            if proc.poll() is None:
                proc.kill()


def _vslab(lab: Path, *args: str | Path, stdin: str | None = None):
    return runner.invoke(app, ["--lab", str(lab), *map(str, args)], input=stdin)


def _latency_timers_at_1_ms(run_dir: Path) -> None:
    """What the udev rule does to every FTDI adapter when it is plugged in (the rig's: in its run dir)."""
    timers = list(run_dir.glob("sysfs/bus/usb-serial/devices/*/latency_timer"))
    assert {t.parent.name for t in timers} >= {"servo_bus"}
    for timer in timers:
        timer.write_text("1\n")


def _bring_up(lab: Path, robot: Path, run_dir: Path) -> Path:
    """Scan, configure and set the latency timer (each step idempotent): the ports file."""
    ports = lab.parent / "ports.json"
    if not ports.exists():
        assert _vslab(lab, "devices", "scan", "--robot", str(robot), "--rig-dir", str(run_dir),
                      "--out", str(ports)).exit_code == 0  # fmt: skip
    done = _vslab(lab, "devices", "configure", "--robot", str(robot), "--ports", str(ports), "--yes")
    assert done.exit_code == 0, done.output
    _latency_timers_at_1_ms(run_dir)
    return ports


@pytest.mark.slow
def test_from_factory_devices_to_a_recorded_session(factory_rig, real_time):
    # real_time: the recording's rates are judged to 1 %, so it runs alone after the workers (beside another
    # worker on a slow machine the pressure board's 250 Hz read 244 Hz over the 3 s, nothing lost)
    lab, robot, run_dir = factory_rig
    ports = lab.parent / "ports.json"
    # 1. scan: every device, the servo bus at the factory's 57,600 baud; a ports file the recorder takes
    scan = _vslab(
        lab, "devices", "scan", "--robot", str(robot), "--rig-dir", str(run_dir), "--out", str(ports)
    )
    assert scan.exit_code == 0, scan.output
    port_map = json.loads(ports.read_text())
    assert set(port_map) == {"servo_bus", "pressure_board", "stepper_board", "tracker"}
    assert all(Path(p).parent == run_dir for p in port_map.values())  # the rig's stable links
    assert "57,600" in scan.output and "9,600" in scan.output and "250,000" in scan.output
    # 2. doctor: each factory trap with its fix, and a non-zero exit
    doctor = _vslab(lab, "devices", "doctor", "--robot", str(robot), "--ports", str(ports))
    assert doctor.exit_code == 1, doctor.output
    text = " ".join(doctor.output.split())
    configure = f"vslab devices configure --robot {robot} --ports {ports}"
    assert "servos answer at 57,600 baud, the description says 1,000,000" in text
    assert "more than one has the same ID" in text
    assert "Return Delay Time" in text and "the description says 0" in text
    assert "latency timer 16 ms, the description says 1 ms" in text
    assert 'ATTR{latency_timer}="1"' in text and "echo 1 | sudo tee" in text
    assert text.count(configure) == 3  # baud, IDs, return delay
    assert "bus budget" in text and "at most 34 Hz" in text  # 57,600 baud, 500 µs, 16 ms
    # 3. configure --yes: the servos, one at a time (the rig connects each), shown then written and verified
    done = _vslab(lab, "devices", "configure", "--robot", str(robot), "--ports", str(ports), "--yes")
    assert done.exit_code == 0, done.output
    assert "q3: written and verified" in done.output and "q2: written and verified" in done.output
    again = _vslab(lab, "devices", "doctor", "--robot", str(robot), "--ports", str(ports))
    assert again.exit_code == 1  # the latency timer is left
    assert "latency timer 16 ms" in again.output and "servo IDs [1, 2]" in again.output
    # 4. every FTDI adapter's latency timer at 1 ms (what the udev rule does): all well
    _latency_timers_at_1_ms(run_dir)
    well = _vslab(lab, "devices", "doctor", "--robot", str(robot), "--ports", str(ports))
    assert well.exit_code == 0, well.output
    assert "all well" in well.output
    ceiling = servo_ceiling_hz(SerialLink(1_000_000, 0.001), 2, 16, 0)
    assert f"at most {ceiling:.0f} Hz" in well.output and SERVO_RATE_HZ < ceiling
    # 5. record with that ports file: the description's rates, nothing lost on the bus vslab set up
    real_time.recording()
    rec = _vslab(lab, "record", "--robot", str(robot), "--ports", str(ports), "--duration", "3",
                 "--session", "first")  # fmt: skip
    assert rec.exit_code == 0, rec.output
    counters = json.loads((lab / "sessions" / "first" / "session.json").read_text())["counters"]
    for topic in RATES_HZ:  # however long the hypervisor stalled the machine, the account adds up
        c = counters[topic]
        assert c["expected"] == c["written"] + c["lost"] + c["dropped"], (topic, c)
    # judged only where the hypervisor left the machine its CPU (a CI run whose recordings lost 0.5–3.5 s to
    # it lost 153 of this servo bus's polls: a guard called after this check failed instead of skipping)
    real_time()
    for topic in ("/servo/state", "/pressure/measured", "/stepper/state", "/tracker/pose"):
        assert f"{topic}: " not in rec.output, rec.output  # a "lost" line names its topic
    for topic, rate in RATES_HZ.items():
        c = counters[topic]
        assert c["lost"] == 0 and c["gaps"] == 0 and c["expected"] == c["written"], (topic, c)
        assert (c["written"] - 1) / ((c["last_ns"] - c["first_ns"]) / 1e9) == pytest.approx(rate, rel=0.01)
        assert c["written"] >= rate * 3 * 0.95, (topic, c)  # the 3 s asked, at least
    servo_row = next(line for line in rec.output.splitlines() if "/servo/state" in line)
    assert servo_row.split("│")[7].strip() == f"{SERVO_RATE_HZ}"  # the table's rate is the stream's own


@pytest.mark.slow
def test_the_first_session_builds(factory_rig):
    """A plan run with the scanned ports (the operator's Enter for each payload), then built: a dataset."""
    lab, robot, run_dir = factory_rig
    ports = _bring_up(lab, robot, run_dir)
    run = _vslab(lab, "run", "campaign", "--plan", "0", "--set", "points=6", "--set", f"robot={robot}",
                 "--ports", str(ports), "--session", "first-run", stdin="\n" * 20)  # fmt: skip
    assert run.exit_code == 0, run.output
    build = _vslab(lab, "build", "--name", "campaign", "--sessions", "first-run", "--workers", "1")
    assert build.exit_code == 0, build.output
    assert "built" in build.output and any((lab / "datasets" / "campaign").glob("*/card.json"))


@pytest.mark.parametrize(
    "args, says",
    [
        (["devices", "doctor", "--robot", "no_such_robot"], "no such robot description"),
        (["devices", "configure", "--robot", "no_such_robot"], "no such robot description"),
        (["devices", "scan", "--robot", "no_such_robot"], "no such robot description"),
        (["devices", "doctor", "--ports", "{not_json}"], "not a ports file"),
        (["devices", "configure", "--ports", "{not_json}", "--yes"], "not a ports file"),
        (["devices", "doctor", "--ports", "{no_port}"], "no such port"),
        (["devices", "configure", "--ports", "{no_port}", "--yes"], "no such port"),
        (["devices", "scan", "--rig-dir", "{tmp}/nowhere"], "no ports.json there"),
    ],
)
def test_broken_input_is_one_error_line(tmp_path, args, says):
    (tmp_path / "not.json").write_text("servo_bus: /dev/ttyUSB0\n")
    (tmp_path / "no_port.json").write_text(json.dumps({"servo_bus": str(tmp_path / "ttyUSB9")}))
    paths = {"not_json": tmp_path / "not.json", "no_port": tmp_path / "no_port.json", "tmp": tmp_path}
    result = _vslab(tmp_path / "lab", *[a.format(**paths) for a in args])
    assert result.exit_code == 2, result.output
    lines = [line for line in result.output.splitlines() if line.strip()]
    assert lines[-1].startswith("error:") and says in " ".join(result.output.split())


@pytest.mark.slow
@pytest.mark.parametrize("command", ["doctor", "configure"])
def test_a_foreign_device_on_the_port_is_one_error_line(factory_rig, tmp_path, command):
    """The servo bus's entry naming the tracker's port: the Aurora answers there, said in one line."""
    lab, robot, run_dir = factory_rig
    ports = tmp_path / "ports.json"
    ports.write_text(json.dumps({"servo_bus": str(run_dir / "tracker")}))
    yes = ["--yes"] if command == "configure" else []
    result = _vslab(lab, "devices", command, "--robot", str(robot), "--ports", str(ports), *yes)
    assert result.exit_code == 2, result.output
    text = " ".join(result.output.split())
    assert [line for line in result.output.splitlines() if line.startswith("error:")] == [
        result.output.strip().splitlines()[-1]
    ]
    assert "AURORA Rev 008 answers there, not a dynamixel" in text


def test_the_latency_timer_is_read_under_the_sysfs_root_given(tmp_path, vsl):
    """An FTDI adapter's timer as Linux shows it (``<root>/bus/usb-serial/devices/ttyUSB0/latency_timer``):
    16 ms against a description that says 1 ms is a problem whose fix is the udev rule; 1 ms is well; a port
    without the file (a USB CDC device) has no timer to set."""
    from acquisition.bringup.doctor import UDEV_RULE, check_latency_timer

    bus = vsl.devices["servo_bus"]
    spec = bus.model_copy(update={"host_link": bus.host_link.model_copy(update={"latency_timer_s": 0.001})})
    timer = tmp_path / "bus/usb-serial/devices/ttyUSB0/latency_timer"
    timer.parent.mkdir(parents=True)
    timer.write_text("16\n")
    finding, seconds = check_latency_timer("servo_bus", spec, "/dev/ttyUSB0", tmp_path)
    assert not finding.ok and seconds == pytest.approx(0.016)
    assert UDEV_RULE in finding.fix and f"echo 1 | sudo tee {timer}" in finding.fix
    timer.write_text("1\n")
    finding, seconds = check_latency_timer("servo_bus", spec, "/dev/ttyUSB0", tmp_path)
    assert finding.ok and seconds == pytest.approx(0.001)
    finding, seconds = check_latency_timer("servo_bus", spec, "/dev/ttyACM0", tmp_path)
    assert finding.ok and seconds == 0.0 and "not an FTDI adapter" in finding.what
