"""``iptm``: the workbench's command line.

Each subcommand lives in its own module under :mod:`iptm.commands` with ``register(subparsers)`` that
adds its parser and sets ``func``; ``func(args)`` returns the exit status. User errors
(:class:`calib.errors.IptmError`) are printed as one line and exit with status 2.
"""
from __future__ import annotations

import argparse
import importlib
import sys
import warnings

from calib import IptmError

# Order = order in `iptm --help`.
COMMANDS = ["run", "simulate", "synth", "ingest", "calibrate", "optimize", "sweep", "params", "plan", "bench"]


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="iptm",
        description=(
            "Prius winter workbench: ingest drive logs, calibrate the hybrid power/thermal model, "
            "optimise power split, engine thermal management and cabin heating by dynamic programming "
            "(Gong et al., IEEE CCTA 2019). Every command that computes figures takes --json FILE."
        ),
    )
    from calib import __version__

    parser.add_argument("--version", action="version", version=f"iptm {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name in COMMANDS:
        try:
            mod = importlib.import_module(f"iptm.commands.{name}")
        except ModuleNotFoundError as exc:
            if exc.name == f"iptm.commands.{name}":
                continue  # not built yet
            raise
        mod.register(sub)
    return parser


_PYTHON_SHOWWARNING = warnings.showwarning


def _show_warning(message, category, filename, lineno, file=None, line=None):
    """The project's own warnings as one plain line; anything else as Python shows it."""
    from calib import IptmWarning

    if issubclass(category, IptmWarning):
        print(f"iptm: warning: {message}", file=file or sys.stderr)
    else:
        _PYTHON_SHOWWARNING(message, category, filename, lineno, file, line)


def main(argv=None) -> int:
    warnings.showwarning = _show_warning
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help()
        return 0
    try:
        return int(args.func(args) or 0)
    except IptmError as exc:
        print(f"iptm {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"iptm {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
