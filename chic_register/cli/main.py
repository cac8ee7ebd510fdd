"""chic-register: register MRI slices of a CHIC fiducial, simulate slices, evaluate accuracy.

This module only assembles the subcommands (one module each in this package,
each with its add_parser and run) and turns failures into exit codes
(docs/interfaces.md section 4): 0 ok, 2 bad input, 3 no trustworthy pose
(no_lock), 4 pose ok but an output (--tfm, --scene, --overlay, OpenIGTLink)
failed: the pose is still printed. main(argv) -> int is testable in-process.
"""

from __future__ import annotations

import argparse
import json
import sys

from chic_register.cli import calibrate, evaluate, exits, precision, reslice, simulate, solve, track
from chic_register.cli import map as map_command  # (the module is named for the subcommand)
from chic_register.cli.console import PROG
from chic_register.errors import ChicRegisterError, NoLock
from chic_register.version import __version__

#: the subcommands, in the order --help lists them
COMMANDS = (solve, map_command, calibrate, precision, simulate, evaluate, reslice, track)
DESCRIPTION = "chic-register: register MRI slices of a CHIC fiducial, simulate slices, evaluate accuracy."


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of every subcommand; each parsed namespace carries its command's ``run``."""
    p = argparse.ArgumentParser(prog=PROG, description=DESCRIPTION)
    p.add_argument("--version", action="version", version=f"{PROG} {__version__}")
    sub = p.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for command in COMMANDS:
        command.add_parser(sub)
    return p


def main(argv=None) -> int:
    """Parse ``argv``, run the command and return its exit code; failures are one line on stderr."""
    args = None
    try:
        args = build_parser().parse_args(argv)  # inside: `--help | head` must not traceback either
        return args.run(args)
    except NoLock as exc:
        if getattr(args, "json", False):
            print(json.dumps({"status": "no_lock", "reason": exc.reason, **exc.detail}, indent=2))
        else:
            print(f"{PROG}: no lock: {exc.reason}", file=sys.stderr)
        return exc.exit_code
    except ChicRegisterError as exc:
        return exits.report(PROG, f"error: {exc}", exc.exit_code)
    except KeyboardInterrupt:
        return exits.report(PROG, "interrupted", 130)
    except BrokenPipeError:  # e.g. `chic-register ... | head`: the reader left; nothing more to say
        return exits.broken_pipe()
    except OSError as exc:  # an output that cannot be written (disk full, permission, vanished folder)
        return exits.os_error(PROG, exc)


if __name__ == "__main__":
    sys.exit(main())
