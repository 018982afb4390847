"""Shared plumbing of Slinger's command-line entry points (runtime, plant, training, evaluation,
diagnosis): logging set-up, argument parsing, and SIGINT/SIGTERM -> stop event."""

from __future__ import annotations

import argparse
import logging
import signal
import threading
from collections.abc import Callable

LOG_FORMAT = "%(asctime)s %(levelname)s %(name)s: %(message)s"


def module_main(
    prog: str,
    description: str,
    build_parser: Callable[[argparse.ArgumentParser], None],
    run: Callable[[argparse.Namespace], int],
    argv: list[str] | None = None,
    intermixed: bool = False,
) -> int:
    """``python -m <module>``: INFO logging, parse ``argv`` with ``build_parser``, return ``run``'s code.

    ``intermixed``: options may stand between positional arguments (``what --out X a b``;
    argparse's ``parse_intermixed_args``)."""
    logging.basicConfig(level=logging.INFO, format=LOG_FORMAT)
    parser = argparse.ArgumentParser(prog=prog, description=description.strip().splitlines()[0])
    build_parser(parser)
    args = parser.parse_intermixed_args(argv) if intermixed else parser.parse_args(argv)
    return int(run(args) or 0)


def stop_on_signals(stop: threading.Event | None = None) -> threading.Event:
    """An event set by SIGINT or SIGTERM (handlers are installed only from the main thread)."""
    stop = stop or threading.Event()
    if threading.current_thread() is threading.main_thread():
        for sig in (signal.SIGINT, signal.SIGTERM):
            signal.signal(sig, lambda *_: stop.set())
    return stop
