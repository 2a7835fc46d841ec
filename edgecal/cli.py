"""The ``edgecal`` command line: one sub-command per module in edgecal/commands/.

Each command module provides ``add_parser(subparsers) -> argparse.ArgumentParser`` and
``run(args) -> int``. User errors (EdgecalError) become one line on stderr and a non-zero exit code;
only a bug in edgecal itself shows a traceback.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import re
import sys
from collections.abc import Sequence

from edgecal.errors import EdgecalError
from edgecal.runtime import quiet_opencv_log, tune_allocator
from edgecal.version import __version__

# Order here is the order in `edgecal --help`.
COMMAND_MODULES = (
    "edgecal.commands.detect",
    "edgecal.commands.run",
    "edgecal.commands.listen",
    "edgecal.commands.keys",
    "edgecal.commands.collect",
    "edgecal.commands.calibrate",
    "edgecal.commands.render",
    "edgecal.commands.sources",
    "edgecal.commands.capture",
    "edgecal.commands.record",
    "edgecal.commands.demo",
)


_RST_ROLE = re.compile(r":(?:func|class|meth|mod|attr|data|obj|ref):`~?([^`]+)`")
_RST_LITERAL = re.compile(r"``([^`]+)``")


def plain_text(text: str | None) -> str | None:
    """``text`` without reStructuredText markup, for the terminal.

    Command descriptions are often the module docstring, written for the API docs; ``--help`` should
    show ``edgecal run`` as edgecal run and :func:`detect` as detect, and a literal block's ``::`` as ``:``.
    """
    if not text:
        return text
    text = _RST_ROLE.sub(r"\1", text)
    text = _RST_LITERAL.sub(r"\1", text)
    return re.sub(r"::$", ":", text, flags=re.MULTILINE)


def build_parser() -> argparse.ArgumentParser:
    """The argument parser with every sub-command registered."""
    parser = argparse.ArgumentParser(
        prog="edgecal",
        description="Chessboard detection, one-shot stereo calibration and live robot pose.")
    parser.add_argument("--version", action="version", version=f"edgecal {__version__}")
    parser.add_argument("-v", "--verbose", action="count", default=0, help="more log output (-vv for debug)")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True
    for name in COMMAND_MODULES:
        module = importlib.import_module(name)
        p = module.add_parser(sub)
        p.set_defaults(_run=module.run)
        # One place cleans what every command shows, so no module has to write its docstring twice.
        p.description = plain_text(p.description)
        p.epilog = plain_text(p.epilog)
        for action in p._actions:
            action.help = plain_text(action.help)
    return parser


def _missing_package(exc: ImportError) -> int:
    """One line for a Python package this environment lacks (an install older than the code, a broken
    venv): every command's module is imported to build the parser, so without this one missing package
    of one command ends every command in a traceback."""
    name = exc.name or str(exc)
    print(f"edgecal: error: the Python package {name!r} is missing from this environment: reinstall edgecal "
          "(pip install -e . in its checkout, or make .venv/.installed)", file=sys.stderr)
    return 2


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``edgecal`` console script."""
    try:
        parser = build_parser()
    except ImportError as exc:
        return _missing_package(exc)
    args = parser.parse_args(argv)
    level = logging.WARNING - 10 * min(args.verbose, 2)
    logging.basicConfig(level=level, format="%(asctime)s %(levelname)s %(name)s: %(message)s", stream=sys.stderr)
    # Every command is its own process and most process images (the daemon for weeks): tune glibc here,
    # not on `import edgecal`, which must leave a host program's allocator alone.
    tune_allocator()
    quiet_opencv_log(verbose=args.verbose > 0)
    try:
        return int(args._run(args) or 0)
    except EdgecalError as exc:
        print(f"edgecal: error: {exc}", file=sys.stderr)
        return exc.exit_code
    except KeyboardInterrupt:
        print("edgecal: interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:
        # `edgecal detect ... | head` closes the pipe early: not an error.
        return 0


if __name__ == "__main__":
    sys.exit(main())
