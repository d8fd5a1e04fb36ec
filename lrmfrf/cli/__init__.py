"""Command line: ``lrmfrf fit``, ``diagnose``, ``example-data`` and ``demo``.

Examples
--------
Copy the shipped example into the current folder and estimate its FRF (the
CSV's time column gives the fast sample time, 0.5 ms)::

    lrmfrf example-data
    lrmfrf fit wafer_stage_example.csv --F 3 --out results

writes ``results/frf.csv``, ``results/frf.npz``, ``results/bode.png`` and
``results/report.txt``. With several data files each gets its own subfolder
``results/<file stem>/``.

Errors (missing file, bad column, NaN, lengths that do not match ``F``, a
sample time that contradicts the file, an existing output without
``--force`` ...) end the program with exit status 1 and one line on standard
error naming the file, the problem and the fix; ``--debug`` shows the
traceback instead. Usage errors exit with status 2. Python warnings are shown
as one ``lrmfrf: warning:`` line each (none with ``--quiet``). The input files
are never modified, and the outputs of a data file are written all or
nothing: everything is computed first, then the files go through temporary
files and ``os.replace``, and a failure leaves none of them behind.

One module per subcommand: :mod:`lrmfrf.cli.fit`, :mod:`lrmfrf.cli.diagnose`,
:mod:`lrmfrf.cli.example_data`, :mod:`lrmfrf.cli.demo`; shared parts in
:mod:`lrmfrf.cli._common`.
"""

from __future__ import annotations

import logging
import sys

from . import demo, diagnose, example_data, fit
from ._common import PROG, CLIError, CLIUsageError, Parser, one_line, say
from ._common import warnings_to_lines as _warnings_to_lines

__all__ = ["CLIError", "CLIUsageError", "build_parser", "main"]

logger = logging.getLogger("lrmfrf.cli")


def build_parser() -> Parser:
    """The ``lrmfrf`` argument parser with its subcommands."""
    from .. import __version__

    parser = Parser(
        prog=PROG,
        description="Fast-rate FRF identification beyond the Nyquist frequency of "
        "a slow-rate sensor (local rational modelling).",
    )
    parser.add_argument(
        "--version", action="version", version=f"%(prog)s {__version__}"
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=Parser)
    sub.required = True
    for module in (fit, example_data, demo, diagnose):
        module.add_parser(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Run the command line; return the exit status.

    Parameters
    ----------
    argv : list of str, optional
        Arguments without the program name; default ``sys.argv[1:]``.

    Returns
    -------
    int
        0 on success, 1 when a file or a computation failed, 2 for usage
        errors, 130 when interrupted.
    """
    parser = build_parser()
    argv = sys.argv[1:] if argv is None else list(argv)
    args = parser.parse_args(argv)
    args.argv = argv
    _configure_logging(args)
    try:
        with _warnings_to_lines(args):
            return args.handler(args, parser)
    except KeyboardInterrupt:
        if args.debug:
            raise
        say(f"{PROG}: interrupted", error=True)
        return 130
    except Exception as exc:  # one line for the user, traceback with --debug
        if args.debug:
            raise
        say(f"{PROG}: error: {one_line(exc)}", error=True)
        return getattr(exc, "exit_status", 1)


def _configure_logging(args) -> None:
    level = logging.DEBUG if args.debug else (
        logging.ERROR if args.quiet else logging.WARNING
    )
    logging.basicConfig(level=level, format=f"{PROG}: %(levelname)s: %(message)s")
    logging.getLogger("lrmfrf").setLevel(level)
