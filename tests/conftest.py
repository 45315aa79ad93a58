"""Shared fixtures: emulator hosts run in their own process, as on the bench."""

from __future__ import annotations

import contextlib
import subprocess
import sys
from pathlib import Path

import pytest

from acquisition.sim.ptyhost import wait_for_ports


@contextlib.contextmanager
def emulator_host(run_dir: Path, *devices: str, module: str = "acquisition.sim.serve", extra: tuple = ()):
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


@pytest.fixture
def host_factory(tmp_path):
    """``with host_factory('name=module:factory') as ports:`` in a fresh run directory."""

    def start(*devices: str, module: str = "acquisition.sim.serve", extra: tuple = ()):
        return emulator_host(tmp_path / "run", *devices, module=module, extra=extra)

    return start
