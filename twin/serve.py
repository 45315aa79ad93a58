"""Serve emulators built by factories in a separate process (tests, and devices used without the twin).

    python -m twin.serve --run-dir DIR name=package.module:factory [name=...]

Each factory is called with no arguments and returns an :class:`Emulator`. The rig (``vslab rig``) is the
same host with the twin behind the emulators.
"""

from __future__ import annotations

import argparse
import importlib
import logging
from pathlib import Path

from twin.emulators.base import Emulator
from twin.ptyhost import PtyHost


def load_factory(spec: str) -> Emulator:
    """``package.module:factory`` → the emulator the factory builds."""
    module_name, _, attr = spec.partition(":")
    if not attr:
        raise ValueError(f"expected package.module:factory, got {spec!r}")
    return getattr(importlib.import_module(module_name), attr)()


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--run-dir", type=Path, required=True)
    parser.add_argument("devices", nargs="+", help="name=package.module:factory")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.WARNING)
    emulators = {}
    for item in args.devices:
        name, _, spec = item.partition("=")
        emulators[name] = load_factory(spec)
    PtyHost(args.run_dir, emulators).serve_forever()


if __name__ == "__main__":
    main()
