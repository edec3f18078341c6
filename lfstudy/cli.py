"""The ``lfstudy`` command line.

Each sub-command lives in its own module under :mod:`lfstudy.commands`
exposing ``NAME``, ``HELP``, ``add_arguments(parser)`` and ``run(args) -> int``;
they are discovered at start-up, so a new stage adds a command without
touching this file.
"""

from __future__ import annotations

import argparse
import importlib
import pkgutil
import sys
from collections.abc import Sequence

from lfstudy.config import ConfigError

__all__ = ["main", "build_parser"]


def build_parser() -> argparse.ArgumentParser:
    """The argument parser with every discovered sub-command."""
    import lfstudy.commands as commands
    from lfstudy import __version__

    parser = argparse.ArgumentParser(
        prog="lfstudy",
        description="Parametric studies of single-camera light-field (plenoptic) 3-D PIV.",
    )
    parser.add_argument("--version", action="version", version=f"lfstudy {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for info in sorted(pkgutil.iter_modules(commands.__path__), key=lambda m: m.name):
        mod = importlib.import_module(f"lfstudy.commands.{info.name}")
        p = sub.add_parser(mod.NAME, help=mod.HELP, description=mod.HELP)
        mod.add_arguments(p)
        p.set_defaults(_run=mod.run)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``lfstudy`` console script."""
    args = build_parser().parse_args(argv)
    try:
        return int(args._run(args) or 0)
    except (ConfigError, ValueError, OSError) as exc:
        # Bad input, or a file the system refuses (permissions, a full disk): one clear line, no traceback.
        print(f"lfstudy {args.command}: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
