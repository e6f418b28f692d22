"""The ``empm`` command: ``empm synth``, ``empm identify``, ``empm evaluate``.

Each layer registers its own sub-commands through a ``register(subparsers)`` function, so this
module stays a thin dispatcher.
"""

from __future__ import annotations

import argparse
import importlib
import sys

# modules that provide ``register(subparsers)``; each adds its sub-commands
_COMMAND_MODULES = ("empm_gym.perception.synth", "empm_gym.identification.cli", "empm_gym.identification.doctor.cli")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="empm", description="Differentiable MPM for deformable objects")
    sub = parser.add_subparsers(dest="command", required=True)
    for name in _COMMAND_MODULES:
        try:
            mod = importlib.import_module(name)
        except ModuleNotFoundError as exc:  # a layer not built yet
            if exc.name != name:
                raise
            continue
        mod.register(sub)
    return parser


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    return int(args.func(args) or 0)


if __name__ == "__main__":
    sys.exit(main())
