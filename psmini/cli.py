"""The ``psmini`` command.

Each sub-command lives in its own module with two functions, ``register(subparsers)`` and ``run(args) -> int``:
the modules of :mod:`psmini.commands`, and modules that other installed packages name in the ``psmini.commands``
entry-point group (data_synth plugs in ``demo`` and ``synth`` this way, so psmini itself never imports its test
bed). This module discovers them, parses the command line and turns every :class:`~psmini.errors.PsminiError`
into a one-line message on stderr and exit status 1.
"""

from __future__ import annotations

import argparse
import importlib
import importlib.metadata
import logging
import os
import pkgutil
import sys
from collections.abc import Sequence

from psmini import __version__, commands, set_threads
from psmini.errors import PsminiError
from psmini.threads import choose_threads

logger = logging.getLogger("psmini")


def build_parser() -> argparse.ArgumentParser:
    """The argument parser with every sub-command of :mod:`psmini.commands`."""
    parser = argparse.ArgumentParser(
        prog="psmini", description="Close-range photometric stereo of textiles: reconstruct, evaluate, synthesise."
    )
    parser.add_argument("--version", action="version", version=f"psmini {__version__}")
    parser.add_argument("-v", "--verbose", action="store_true", help="log progress details on stderr")
    parser.add_argument("--threads", type=int, metavar="N",
                        help="intra-op threads of this process (default: one per idle core, or OMP_NUM_THREADS; "
                             "psmini batch divides them among its workers)")
    subparsers = parser.add_subparsers(dest="command", metavar="COMMAND")
    modules = {info.name: f"{commands.__name__}.{info.name}" for info in pkgutil.iter_modules(commands.__path__)
               if not info.name.startswith("_")}
    modules.update({entry.name: entry.value for entry in importlib.metadata.entry_points(group="psmini.commands")})
    for name in sorted(modules):
        importlib.import_module(modules[name]).register(subparsers)
    return parser


def quiet_opencv() -> None:
    """Keep OpenCV's own log lines (``[ WARN:0@0.02] global grfmt_png.cpp ...``) off the terminal.

    psmini's errors already say which file is bad and why; OpenCV's warnings would come first and add nothing.
    Sets ``OPENCV_LOG_LEVEL=ERROR`` for this process and the worker processes it starts (unless the user set
    it), and lowers the level of an OpenCV already imported.
    """
    os.environ.setdefault("OPENCV_LOG_LEVEL", "ERROR")
    cv2 = sys.modules.get("cv2")
    if cv2 is not None and os.environ["OPENCV_LOG_LEVEL"] == "ERROR":
        cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_ERROR)


def main(argv: Sequence[str] | None = None) -> int:
    """Run the ``psmini`` command; return its exit status."""
    parser = build_parser()
    args = parser.parse_args(argv)
    if not args.verbose:
        quiet_opencv()
    logging.basicConfig(level=logging.INFO if args.verbose else logging.WARNING, format="%(levelname)s: %(message)s")
    if args.command is None:
        parser.print_help()
        return 2
    try:
        if args.threads is not None:
            set_threads(args.threads)
        else:
            choose_threads()
        return int(args.run(args) or 0)
    except PsminiError as error:
        print(f"psmini {args.command}: error: {error}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print(f"psmini {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
