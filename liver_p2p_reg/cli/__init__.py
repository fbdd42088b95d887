"""The `liver-p2p` command line: dispatches to one module per subcommand.

Building the parser imports no heavy library (torch, Open3D, scipy, matplotlib): `--help` and
argument errors answer at once; each subcommand imports what it needs when it runs.
"""

from __future__ import annotations

import argparse
import contextlib
import importlib
import logging
import re
import signal
import sys
import threading
from collections.abc import Iterator

from liver_p2p_reg import __version__
from liver_p2p_reg.errors import LiverP2PError

# Each module defines `add_parser(subparsers)` and sets `func(args) -> int` on its parser.
_SUBCOMMAND_MODULES = (
    "register_cmd",
    "dataset_cmd",
    "train_cmd",
    "prepare_cmd",
    "benchmark_cmd",
    "bag_cmd",
    "replay_cmd",
    "config_cmd",
    "demo_cmd",
    "soak_cmd",
    "calibrate_cmd",
)


class OneLineErrorParser(argparse.ArgumentParser):
    """argparse's parser with its errors on one line (exit 2), like every other error of the command.

    argparse prints the whole usage block before the message; the usage is one `--help` away.
    Sub-parsers are made of the same class, so the subcommands' errors are one line too.
    """

    def error(self, message: str):  # type: ignore[override]
        self.exit(2, f"{self.prog}: error: {message} (see `{self.prog} --help`)\n")


def build_parser() -> argparse.ArgumentParser:
    """The full argument parser (also used to generate documentation)."""
    parser = OneLineErrorParser(
        prog="liver-p2p",
        description="Automatic complete-to-partial rigid registration of liver surfaces (P2P).",
    )
    parser.add_argument("--version", action="version", version=f"liver-p2p {__version__}")
    parser.add_argument("--debug", action="store_true", help="show tracebacks for unexpected errors")
    parser.add_argument("-q", "--quiet", action="store_true", help="only print errors")
    subparsers = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name in _SUBCOMMAND_MODULES:
        try:
            module = importlib.import_module(f"{__name__}.{name}")
        except ModuleNotFoundError as exc:
            if exc.name != f"{__name__}.{name}":
                raise
            continue  # subcommand not part of this build
        module.add_parser(subparsers)
    return parser


# Options whose value may start with a minus (coordinates): argparse would read `-10,0,5` as an option.
_SIGNED_VALUE_OPTIONS = ("--sensor-origin",)


def attach_signed_values(argv: list[str]) -> list[str]:
    """`--sensor-origin -10,0,5` -> `--sensor-origin=-10,0,5`, so a value typed with a minus sign is a value."""
    out: list[str] = []
    i = 0
    while i < len(argv):
        token = argv[i]
        if token in _SIGNED_VALUE_OPTIONS and i + 1 < len(argv) and re.match(r"^-[\d.]", argv[i + 1]):
            out.append(f"{token}={argv[i + 1]}")
            i += 2
            continue
        out.append(token)
        i += 1
    return out


def _interrupt(signum: int, frame: object) -> None:
    """SIGTERM handler: raise KeyboardInterrupt."""
    raise KeyboardInterrupt


@contextlib.contextmanager
def terminate_as_interrupt() -> Iterator[None]:
    """Within it, SIGTERM (a supervisor's, `timeout`'s, `kill`'s) ends the command as Ctrl-C does, so its cleanup
    runs: the nodes a soak or the demo started are stopped, a recording gets its footer, a training run's workers
    and temporary weights go. Killed by the default action instead, the command would leave its node processes
    answering on their domain. Only in the main thread (where Python delivers signals)."""
    main_thread = threading.current_thread() is threading.main_thread()
    previous = signal.signal(signal.SIGTERM, _interrupt) if main_thread else None
    try:
        yield
    finally:
        if main_thread:
            signal.signal(signal.SIGTERM, previous)


def main(argv: list[str] | None = None) -> int:
    """Entry point; returns the process exit status (0 ok, 1 internal error, 2 bad input)."""
    parser = build_parser()
    args = parser.parse_args(attach_signed_values(sys.argv[1:] if argv is None else list(argv)))
    # Our messages at INFO; other libraries' (scikit-fem's solver lines, ...) only from WARNING up,
    # so they do not interleave with progress bars and tables.
    logging.basicConfig(level=logging.WARNING, format="liver-p2p: %(levelname)s: %(message)s", stream=sys.stderr)
    logging.getLogger("liver_p2p_reg").setLevel(logging.ERROR if args.quiet else logging.INFO)
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    try:
        with terminate_as_interrupt():
            return int(args.func(args) or 0)
    except LiverP2PError as exc:
        print(f"liver-p2p: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("liver-p2p: interrupted", file=sys.stderr)
        return 130
    except Exception as exc:  # never a raw traceback for users; --debug shows it
        if args.debug:
            raise
        if isinstance(exc, OSError) and exc.filename is not None:  # the file system refused a named file
            name = str(exc.filename).removesuffix(".tmp")  # an atomic write's temporary file: the output's name
            print(f"liver-p2p: error: {name}: {exc.strerror or exc}", file=sys.stderr)  # (read-only, disk full)
            return 2
        print(f"liver-p2p: internal error: {type(exc).__name__}: {exc} (rerun with --debug)", file=sys.stderr)
        return 1
