"""``chic-design``: the argument parser and ``main``; each subcommand is a module of this package.

A subcommand module has ``add_parser(subparsers)`` (its flags, plain-text
help) and ``run(args) -> int`` (a thin layer over the library). ``main(argv)
-> int`` is testable in-process. Exit codes: 0 ok, 1 ``check`` found the
design infeasible (or an output could not be written), 2 bad input, 4 an
infeasible design or no feasible design found, 5 the build's output checks
failed, 3 the slicer is missing or failed, 6 the print check found a channel the
toolpaths close, narrow or overhang, 130 interrupted. Every failure is one line on stderr, never a traceback.
"""

from __future__ import annotations

import argparse
import sys

from chic_design import __version__
from chic_design.cli import build, check, optimize, printcheck, schema
from chic_design.errors import ChicDesignError
from chic_register.cli import exits
from chic_register.errors import ChicRegisterError

PROG = "chic-design"
DESCRIPTION = ("Build a CHIC (or Z-frame) MRI fiducial from a design spec, check its feasibility, "
               "print the spec schema, or search for the best design.")
#: The subcommands, in the order --help lists them.
COMMANDS = (build, check, printcheck, schema, optimize)


def make_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog=PROG, description=DESCRIPTION)
    p.add_argument("--version", action="version", version=f"{PROG} {__version__}")
    sub = p.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for command in COMMANDS:
        command.add_parser(sub).set_defaults(run=command.run)
    return p


def main(argv=None) -> int:
    try:
        args = make_parser().parse_args(argv)  # inside: `--help | head` must not traceback either
        return args.run(args)
    except (ChicDesignError, ChicRegisterError) as exc:  # the geometry file is chic_register's
        return exits.report(PROG, f"error: {exc}", exc.exit_code)
    except KeyboardInterrupt:
        return exits.report(PROG, "interrupted", 130)
    except BrokenPipeError:  # e.g. `chic-design schema | head`: the reader left; nothing more to say
        return exits.broken_pipe()
    except OSError as exc:  # an output that cannot be written (disk full, permission, vanished folder)
        return exits.os_error(PROG, exc)


if __name__ == "__main__":
    sys.exit(main())
