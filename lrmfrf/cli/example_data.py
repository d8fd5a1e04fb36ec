"""``lrmfrf example-data``: copy the shipped example records into a folder."""

from __future__ import annotations

from pathlib import Path

from ._common import add_common, check_out_folder, output_folder, say

__all__ = ["EXAMPLE_FILES", "add_parser", "run"]

EXAMPLE_FILES = ("wafer_stage_example.csv", "wafer_stage_example.npz")


def add_parser(sub) -> None:
    """Add the ``example-data`` subcommand to ``sub``."""
    example = sub.add_parser(
        "example-data",
        help="copy the shipped example data into a folder",
        description="Copy the shipped example records (wafer stage, N=1200, F=3, "
        f"Ts=0.5 ms) {', '.join(EXAMPLE_FILES)} into --out.",
    )
    example.add_argument("--out", type=output_folder, default=Path("."),
                         metavar="DIR",
                         help="destination folder (default: the current folder)")
    add_common(example)
    example.set_defaults(handler=run)


def run(args, parser) -> int:
    """Run ``lrmfrf example-data``: both files or neither."""
    from importlib.resources import files

    from ..io import atomic_group, check_output_path

    source = files("lrmfrf") / "data"
    check_out_folder(args.out)
    targets = [args.out / name for name in EXAMPLE_FILES]
    for target in targets:
        check_output_path(target, overwrite=args.force)
    with atomic_group(overwrite=args.force) as group:
        for name, target in zip(EXAMPLE_FILES, targets, strict=True):
            group.write_bytes(target, (source / name).read_bytes())
    if not args.quiet:
        for target in targets:
            say(f"wrote {target}")
    return 0
