"""``lrmfrf demo``: simulate the wafer stage, compare LRM, LPM and SA."""

from __future__ import annotations

from pathlib import Path

from ._common import (
    PROG,
    CLIError,
    add_common,
    check_out_folder,
    finite_float,
    nonnegative_int,
    one_line,
    output_folder,
    say,
)

__all__ = ["add_parser", "run"]


def add_parser(sub) -> None:
    """Add the ``demo`` subcommand to ``sub``."""
    demo = sub.add_parser(
        "demo",
        help="simulate the wafer stage, compare LRM, LPM and SA",
        description="Simulate the OAT-like wafer stage, identify it with LRM, LPM "
        "and SA, print an error table and write figures into --out.",
    )
    demo.add_argument("--out", type=output_folder, default=Path("lrmfrf-demo"),
                      metavar="DIR", help="output folder (default ./lrmfrf-demo)")
    demo.add_argument("--seed", type=nonnegative_int, default=0,
                      help="random seed (default 0)")
    demo.add_argument("--snr", type=finite_float, default=45.0, metavar="DB",
                      help="output signal-to-noise ratio in dB (default 45)")
    add_common(demo)
    demo.set_defaults(handler=run)


def run(args, parser) -> int:
    """Run ``lrmfrf demo``."""
    try:
        from ..demo import run_demo
    except ImportError as exc:
        raise CLIError(
            f"the demo is not available in this installation ({one_line(exc)}). "
            "Reinstall lrmfrf or update it."
        ) from exc
    check_out_folder(args.out)
    result = run_demo(args.out, seed=args.seed, snr_db=args.snr, overwrite=args.force)
    if not args.quiet:
        say(result.table)
        for path in result.files:
            say(f"wrote {path}")
        for note in getattr(result, "notes", ()):
            say(f"{PROG}: warning: {note}", error=True)
    return 0
