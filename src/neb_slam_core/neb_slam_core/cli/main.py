"""``neb-slam``: the offline command line.

Each sub-command lives in its own module of this package exposing ``HELP`` (one line),
``add_arguments(parser)`` and ``run(args) -> int``. Modules are imported only when their command runs,
so ``neb-slam eval`` does not pay for torch or rosbags.

Exit status: 0 on success, 2 for bad input (one line naming the file, option or value), 130 after Ctrl-C
and 143 after SIGTERM, which every command handles as it handles Ctrl-C (:mod:`.interrupt`).
"""

from __future__ import annotations

import argparse
import importlib
import logging
import sys

from ..errors import NebSlamError
from .interrupt import describe, exit_status, sigterm_interrupts

#: sub-command -> module in this package
COMMANDS: dict[str, str] = {
    "synth": "synth",
    "convert": "convert",
    "info": "info",
    "eval": "evaluate",
    "run": "run",
    "vocab": "vocab",
}


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="neb-slam", description="NeB-SLAM: neural-block RGB-D SLAM, offline tools.")
    parser.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for name, module_name in COMMANDS.items():
        module = importlib.import_module(f"{__package__}.{module_name}")
        p = sub.add_parser(
            name, help=module.HELP, description=module.__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
        )
        module.add_arguments(p)
        p.set_defaults(_module=module)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    logging.basicConfig(
        level=logging.DEBUG if args.verbose else logging.INFO, format="%(levelname)s %(name)s: %(message)s"
    )
    try:
        with sigterm_interrupts():
            return int(args._module.run(args) or 0)
    except NebSlamError as exc:
        print(f"neb-slam {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt as exc:
        print(f"neb-slam {args.command}: interrupted ({describe(exc)})", file=sys.stderr)
        return exit_status(exc)


if __name__ == "__main__":
    sys.exit(main())
