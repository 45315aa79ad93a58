"""Shared fixtures: the robot descriptions; emulator hosts run in their own process, as on the bench."""

from __future__ import annotations

import contextlib
import os
import re
import signal
import socket
import subprocess
import sys
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

# Under pytest-xdist (`make check` and `make test` run one worker per core): each worker computes on one
# thread. Two processes of torch's, numba's or BLAS's threads on the same cores spin-wait on each other (a
# paper net's epoch 6.7× slower beside another): the fast tier took 192 s on 2 workers of 2 threads each,
# 92 s on 2 workers of one, against 145 s in one process of 2. Set before numpy, torch or numba is imported;
# the commands the tests start inherit it.
if os.environ.get("PYTEST_XDIST_WORKER"):
    for threads in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS", "NUMBA_NUM_THREADS"):
        os.environ.setdefault(threads, "1")

import numpy as np
import pytest
from machine_stalls import RealTimeCheck
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory

from acquisition.recorder.sessions import SessionStore
from acquisition.schemas.fast_read import read_fixed_topics
from models.robot import load_robot
from pipeline.lab import Lab
from twin.ptyhost import wait_for_ports

# The CLI's batch commands (train, simulate, build) lower their own process's priority for good; the tests
# call them in this process, which must keep its priority for the real-time tests that follow.
os.environ.setdefault("VSLAB_BATCH_NICE", "0")


@contextlib.contextmanager
def emulator_host(run_dir: Path, *devices: str, module: str = "twin.serve", extra: tuple = ()):
    """Start ``python -m module --run-dir run_dir *extra *devices`` and yield its published ports."""
    proc = subprocess.Popen([sys.executable, "-m", module, "--run-dir", str(run_dir), *extra, *devices])
    try:
        yield wait_for_ports(run_dir, timeout_s=60)
    finally:
        proc.terminate()
        try:
            assert proc.wait(timeout=10) == 0, "the emulator host must stop cleanly on SIGTERM"
        finally:
            if proc.poll() is None:
                proc.kill()


# A test run started in the background by a non-interactive shell (`make test &`, nohup) inherits SIGINT
# ignored, and so would every process it starts: the Ctrl-C tests would then time out on a child that never
# sees the signal. An ignored signal stays ignored across exec, a handled one does not, so handling it here
# gives the children the default disposition, as a terminal's foreground job has.
if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
    signal.signal(signal.SIGINT, signal.default_int_handler)


@contextlib.contextmanager
def absent_service_ports():
    """Two ports on 127.0.0.1 where a service is not there: one bound and closed (connections refused) and one
    that listens but never reads or writes (connections accepted, then silence), as ``(closed, silent)``."""
    with socket.socket() as closed:
        closed.bind(("127.0.0.1", 0))
        free = closed.getsockname()[1]
    with socket.socket() as silent:
        silent.bind(("127.0.0.1", 0))
        silent.listen(8)  # the kernel accepts connections; nobody reads or writes them
        yield free, silent.getsockname()[1]


@pytest.fixture(scope="module")
def popup_rig(tmp_path_factory):
    """A POPUP rig for one test module: (its run directory, the port of its CAN adapter)."""
    run_dir = tmp_path_factory.mktemp("popup-rig")
    with emulator_host(run_dir, module="twin.rig", extra=("--robot", "popup")) as ports:
        yield run_dir, ports["can_bus"]


@pytest.fixture
def host_factory(tmp_path):
    """``with host_factory('name=module:factory') as ports:`` in a fresh run directory."""

    def start(*devices: str, module: str = "twin.serve", extra: tuple = ()):
        return emulator_host(tmp_path / "run", *devices, module=module, extra=extra)

    return start


def ros2_decodes_as_fast_path(part: Path) -> dict[str, int]:
    """Decode every fixed-layout message of ``part`` with mcap-ros2-support (the reference decoder) and check
    each field against the fast chunk reader's; returns the messages checked per topic."""
    fast = read_fixed_topics(part)
    seen = {topic: 0 for topic in fast}
    with open(part, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        for _, channel, message, decoded in reader.iter_decoded_messages(log_time_order=False):
            if channel.topic not in fast:
                continue
            data = fast[channel.topic]
            i = message.sequence  # the writer numbers each topic's messages from 0, in log-time order
            assert data.log_time[i] == message.log_time
            row = data.rows[i]
            for name in row.dtype.names[1:]:
                np.testing.assert_array_equal(np.asarray(getattr(decoded, name)), row[name])
            seen[channel.topic] += 1
    assert seen == {topic: len(d) for topic, d in fast.items()}
    return seen


@pytest.fixture
def ros2_agrees():
    """The check of :func:`ros2_decodes_as_fast_path`, for tests that write sessions."""
    return ros2_decodes_as_fast_path


@pytest.fixture(scope="session")
def campaign_dataset(tmp_path_factory):
    """A small twin campaign built into a dataset: (lab directory, dataset version, D as a DataFrame).
    600 settled points on 8 benches (≈ 10 s once per test run)."""
    from pipeline.build import build
    from pipeline.dataset_store import DatasetStore
    from twin.runner import simulate_experiment

    lab = tmp_path_factory.mktemp("campaign-lab")
    simulate_experiment(
        "campaign", SessionStore(lab / "sessions"), seed=11, benches=8, overrides={"points": 600}
    )
    report = build(sorted((lab / "sessions").iterdir()), Lab(lab), "campaign")
    data, _ = DatasetStore(lab / "datasets").load("campaign", report.version)
    return lab, report.version, data


@pytest.fixture(scope="session")
def hard_labs(tmp_path_factory):
    """The small campaign on the twin with its unmodelled effects on (vsl_unmodelled), built twice, each in a
    lab of its own: as drawn and its repeat (the same points, each bench shuffled). {order: (lab, dataset
    version)}; ≈ 30 s once per run."""
    from pipeline.build import build
    from twin.runner import simulate_experiment

    out = {}
    for order in ("drawn", "shuffled"):
        lab = tmp_path_factory.mktemp(f"hard-{order}")
        overrides = {"points": 600, "robot": "vsl_unmodelled", "visit_order": order}
        simulate_experiment(
            "campaign", SessionStore(lab / "sessions"), seed=11, benches=8, overrides=overrides
        )
        out[order] = (lab, build(sorted((lab / "sessions").iterdir()), Lab(lab), "campaign").version)
    return out


@pytest.fixture(scope="session")
def hard_campaigns(hard_labs):
    """(D, D of the repeat) of :func:`hard_labs`."""
    from pipeline.dataset_store import DatasetStore

    return tuple(
        DatasetStore(lab / "datasets").load("campaign", version)[0] for lab, version in hard_labs.values()
    )


# The robot descriptions (frozen models): loaded once for the whole run.
@pytest.fixture(scope="session")
def vsl():
    return load_robot("vsl")


@pytest.fixture(scope="session")
def rigid():
    return load_robot("vsl_rigid")


@pytest.fixture(scope="session")
def popup():
    return load_robot("popup")


def pytest_configure() -> None:
    """Where PYTHONDONTWRITEBYTECODE is set (as on this project's machines), pytest would rewrite the asserts
    of every test module again in every process: 3.7 of the 12 s each worker took to collect the fast tier.
    The rewritten modules are cached in tests/__pycache__ (ignored by git), as without the variable; the
    project's own modules are byte-compiled by the Makefile."""
    sys.dont_write_bytecode = False


@pytest.hookimpl(tryfirst=True)  # before -m deselects by marker, and before xdist reads the groups
def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """A test that judges a real-time recording (it asks for ``real_time``) is marked ``real_time``: make test
    and make check run those alone, after the others' workers (``make test-under-load`` runs them with every
    core busy). The tests that read the tutorials' run (``tutorial_run``: the quick main job, ~5 min) are one
    group: under ``--dist loadgroup`` one worker runs them, so the main job runs once, not once a worker. So
    are the tests of a module that share a module- or class-scoped fixture: spread over both workers, each
    worker made it (a simulated campaign, a built site: ~65 CPU-seconds of the suite made twice)."""
    for item in items:
        fixtures = getattr(item, "fixturenames", ())
        if "real_time" in fixtures:
            item.add_marker(pytest.mark.real_time)
        if "tutorial_run" in fixtures:
            item.add_marker(pytest.mark.xdist_group(TUTORIALS_GROUP))
        elif _shares_a_fixture(item):
            item.add_marker(pytest.mark.xdist_group(item.nodeid.split("::")[0]))


def _shares_a_fixture(item: pytest.Item) -> bool:
    """Whether ``item`` uses a fixture made once for its module or class (session ones are made once a
    worker whatever the grouping)."""
    definitions = getattr(getattr(item, "_fixtureinfo", None), "name2fixturedefs", {})
    return any(defs and defs[-1].scope in ("module", "class", "package") for defs in definitions.values())


TUTORIALS_GROUP = "tutorials"


@pytest.fixture
def real_time(request: pytest.FixtureRequest) -> Iterator[RealTimeCheck]:
    """Call it after a real-time recording, before asserting its rates: it skips the test, saying so, when
    the machine itself stopped for nearly as long as a polled daemon may fall behind and catch up
    (``MAX_LAG_S``, 50 ms): one such pause, all at once, loses samples whatever the code does. Load on the
    machine is the tests' to hold; CPUs that are not there are no computer a lab records on. The witness is
    a stall watch on each CPU (``tests/machine_stalls.py``): a process held there at real-time priority that
    waited ``STALL_S`` (40 ms) to be woken means that CPU ran nothing. The recording is taken to start with
    the test; a test that does other work first calls ``real_time.recording()`` as it starts. Given the
    recorder (``real_time(rec)``), what it saw goes into the test's report with how far each daemon fell
    behind: a failure says whether the machine or the code lost the samples."""
    check = RealTimeCheck(request.node)
    yield check
    check.close()


# ------------------------------------------------------------------------------- the tutorials, run once
TUTORIALS = ("twin-end-to-end", "paper-figures", "first-session")  # docs/tutorials/, in the site's nav order
DOCS = Path(__file__).resolve().parents[1] / "docs"
_FENCE = re.compile(r"^(?P<indent>[ \t]*)(?P<fence>`{3,}|~{3,})[ \t]*(?P<lang>[\w+-]*)[^\n]*$")


def tutorial_blocks(page: Path) -> list[str]:
    """The ``sh`` fenced blocks of a Markdown page, in order (indented fences, as in admonitions, included):
    the commands a reader runs; ``text`` blocks show output and are never run."""
    blocks, lines, k = [], page.read_text().splitlines(), 0
    while k < len(lines):
        m = _FENCE.match(lines[k])
        k += 1
        if m is None:
            continue
        body, indent, fence = [], m["indent"], m["fence"]
        while k < len(lines) and not lines[k].strip().startswith(fence):
            body.append(lines[k][len(indent) :] if lines[k].startswith(indent) else lines[k].lstrip())
            k += 1
        k += 1
        if m["lang"] == "sh":
            blocks.append("\n".join(body) + "\n")
    return blocks


@dataclass
class TutorialRun:
    """The tutorials' ``sh`` blocks run in order in one working directory: each (page, block, exit status,
    output); the run stops at the first block that fails."""

    workdir: Path
    results: list[tuple[str, str, int, str]] = field(default_factory=list)
    left_running: list[str] = field(default_factory=list)  # processes a tutorial started and did not stop

    def failure(self) -> str | None:
        """What a failed block ran and said, or None when every block succeeded."""
        for page, block, rc, output in self.results:
            if rc != 0:
                said = f"\n--- its output ---\n{output}"
                return f"docs/tutorials/{page}.md: this block exited {rc}:\n{block}{said}"
        return None

    def output_of(self, word: str) -> str:
        """The output of the blocks whose commands contain ``word``."""
        return "".join(output for _, block, _, output in self.results if word in block)


@pytest.fixture(scope="session")
def tutorial_run(tmp_path_factory):
    """Every tutorial's ``sh`` blocks, in nav order, each with ``bash -euo pipefail`` in one fresh directory
    with the project's ``vslab`` first on PATH, as a reader following them does (≈ 3 min: the twin tutorial
    runs the quick main job, which tests/test_main_job.py then inspects instead of running it again). What a
    tutorial started and did not stop (the rig, if a block failed before its ``kill``) is stopped here."""
    run = TutorialRun(tmp_path_factory.mktemp("tutorials"))
    env = os.environ | {"PATH": f"{Path(sys.executable).parent}{os.pathsep}{os.environ.get('PATH', '')}"}
    try:
        for page, block in (
            (p, b) for p in TUTORIALS for b in tutorial_blocks(DOCS / "tutorials" / f"{p}.md")
        ):
            command = ["bash", "-euo", "pipefail", "-c", block]
            done = subprocess.run(command, cwd=run.workdir, env=env, stdout=subprocess.PIPE,
                                  stderr=subprocess.STDOUT, text=True, timeout=1800)  # fmt: skip
            run.results.append((page, block, done.returncode, done.stdout))
            if done.returncode != 0:
                break
        run.left_running = _stop_left_running(run.workdir)
        yield run
    finally:
        _stop_left_running(run.workdir)


def _stop_left_running(workdir: Path, grace_s: float = 10.0) -> list[str]:
    """Stop every process still running in ``workdir`` once ``grace_s`` has let the stopping ones end (a rig
    given SIGTERM takes a moment): what was left, one line each."""
    import psutil

    def inside(p: psutil.Process) -> bool:
        with contextlib.suppress(psutil.Error, OSError):
            return Path(p.cwd()).is_relative_to(workdir)
        return False

    running = [p for p in psutil.process_iter() if p.pid != os.getpid() and inside(p)]
    _, left = psutil.wait_procs(running, timeout=grace_s)
    said = []
    for p in left:
        with contextlib.suppress(psutil.Error):
            said.append(f"{p.pid}: {' '.join(p.cmdline())}")
            p.terminate()
    _, stubborn = psutil.wait_procs(left, timeout=5)
    for p in stubborn:
        with contextlib.suppress(psutil.Error):
            p.kill()
    return said


def perturbed_popup(path, k_factor: float, c_factor: float):
    """configs/robots/popup.yaml, still named popup, with link 2's stiffness × k_factor and damping × c_factor
    written to ``path`` (link 1 follows link 2's table, so it changes too); the links' yield torques scale
    with a stiffer link, as the description's own check τ_y ≥ k·δ_h asks. Returns ``path``."""
    import yaml

    from models.robot import robot_path

    data = yaml.safe_load(robot_path("popup").read_text())
    for link in data["links"]:
        link["hysteresis"]["tau_y_nm"] *= max(k_factor, 1.0)
        if link["name"] == "link2":
            table = link["table"]
            table["stiffness_nm_per_rad"] = [k * k_factor for k in table["stiffness_nm_per_rad"]]
            table["damping_nms_per_rad"] = [c * c_factor for c in table["damping_nms_per_rad"]]
    path.write_text(yaml.safe_dump(data))
    return path
