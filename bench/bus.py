"""What each device's link carries, computed and reached on the rig: the servo bus at 57,600 / 1 M / 4 M baud
behind an adapter whose latency timer is 16 ms (the driver's default) or 1 ms (a udev rule's).

    python bench/bus.py [--robot vsl] [--seconds 2]

For each case the robot description is copied with the servo bus at that baud and latency timer, a rig
serves it (``twin.rig``, the wire-true pty host), and the project's servo driver reads it back to back (asking
for more than the ceiling: the recorder itself refuses a rate above it) for ``--seconds``. Printed per case:
asked / ceiling (``bus_budget.servo_bus_ceiling_hz``) / reached / reached ÷ ceiling, and the machine's load
average. Exit status 1 if a reached rate is above its ceiling or below 85 % of it.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from acquisition.devices.bus_budget import reply_timeout_s, servo_bus_ceiling_hz
from acquisition.devices.servo_bus import ServoBus
from models.robot import RobotDescription, load_robot
from twin.rig_process import rig_ports, rig_process

BAUDS = (57_600, 1_000_000, 4_000_000)
LATENCY_TIMERS_S = (0.016, 0.001)
LOWEST_FRACTION = 0.85  # of the ceiling: a reached rate below it fails (the acceptance: within 15 %)


def servo_case(robot: RobotDescription, baud: int, latency_timer_s: float) -> RobotDescription:
    """``robot`` with its servo bus at ``baud`` behind an adapter with a ``latency_timer_s`` timer."""
    spec = robot.devices["servo_bus"]
    link = spec.host_link.model_copy(update={"latency_timer_s": latency_timer_s})
    devices = dict(robot.devices)
    devices["servo_bus"] = spec.model_copy(update={"baud": baud, "host_link": link})
    return robot.model_copy(update={"devices": devices})


def reached_hz(robot: RobotDescription, seconds: float) -> float:
    """Sync Reads per second of the servo driver, back to back, against a rig of ``robot``."""
    spec = robot.devices["servo_bus"]
    with tempfile.TemporaryDirectory(prefix="bus-") as tmp, rig_process(robot, Path(tmp)) as proc:
        ports = rig_ports(Path(tmp), proc)
        timeout = reply_timeout_s(spec.host_link.latency_timer_s)  # as the recorder's servo source waits
        with ServoBus(
            ports["servo_bus"], ids=list(spec.ids.values()), baud=spec.baud, reply_timeout_s=timeout
        ) as bus:
            for _ in range(5):  # the first reads step the twin from its start
                bus.read_state()
            n, start = 0, time.monotonic()
            while time.monotonic() - start < seconds:
                bus.read_state()
                n += 1
            return n / (time.monotonic() - start)


def can_bus_load_lines() -> list[str]:
    """POPUP's CAN bus load at its configured rates.

    INTEGRATION POINT (issue 31, "can" part): print the CAN bus load of POPUP's configured rates here, from
    the function the CAN bus work provides; nothing is printed until it is joined."""
    return []


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--robot", default="vsl")
    parser.add_argument("--seconds", type=float, default=2.0)
    args = parser.parse_args()
    robot = load_robot(args.robot)
    failed = False
    print(
        f"{'device':<12} {'baud':>9} {'timer ms':>8} {'asked':>8} {'ceiling':>8} {'reached':>8} {'÷ ceil':>7}"
    )
    for baud in BAUDS:
        for latency in LATENCY_TIMERS_S:
            case = servo_case(robot, baud, latency)
            ceiling = servo_bus_ceiling_hz(case.devices["servo_bus"])
            reached = reached_hz(case, args.seconds)
            ratio = reached / ceiling
            bad = ratio > 1.0 or ratio < LOWEST_FRACTION
            failed |= bad
            cells = (baud, f"{latency * 1e3:.0f}", "max", f"{ceiling:.1f}", f"{reached:.1f}", f"{ratio:.3f}")
            print(f"{'servo_bus':<12} " + " ".join(f"{c:>9}" for c in cells) + ("  FAIL" if bad else ""))
    for line in can_bus_load_lines():
        print(line)
    load = os.getloadavg()
    print(f"load average {load[0]:.2f} {load[1]:.2f} {load[2]:.2f} on {os.cpu_count()} cores")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
