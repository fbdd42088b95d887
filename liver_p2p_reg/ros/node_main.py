"""What the package's rclpy nodes share: their main(), their parameters from a config dataclass, logging onto rclpy."""

from __future__ import annotations

import dataclasses
import logging
import os
import sys
import threading
from collections.abc import Callable
from typing import Any, TypeVar

import rclpy
from rcl_interfaces.msg import ParameterDescriptor
from rclpy.exceptions import ParameterException
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy
from rclpy.logging import get_logger
from rclpy.node import Node

from liver_p2p_reg.errors import LiverP2PError

ConfigT = TypeVar("ConfigT")
# Seconds the teardown (destroy_node, rclpy shutdown) may take before an exit_process node leaves without
# it: DDS teardown has been seen to block for more than 10 s on a loaded host with stale shared-memory
# ports, and a robot's launch system should see its SIGINT answered, not escalate to SIGKILL.
EXIT_GRACE_S = 10.0


def _exit_after(grace_s: float, status: int, name: str) -> threading.Timer:
    """A started daemon timer that ends the process with `status` after `grace_s`, saying why on stderr."""

    def leave() -> None:
        sys.stderr.write(f"[{name}] teardown took more than {grace_s:g} s; exiting without waiting for it\n")
        sys.stderr.flush()
        os._exit(status)

    timer = threading.Timer(grace_s, leave)
    timer.daemon = True
    timer.start()
    return timer


def run_node(
    make_node: Callable[[], Node],
    name: str,
    args: list[str] | None,
    *,
    exit_process: bool,
    exit_grace_s: float = EXIT_GRACE_S,
) -> int:
    """A node's `main()`, the Jazzy idiom (rclpy.init() returns None); the exit status.

    Ctrl-C and an external shutdown (SIGTERM) end it quietly; a LiverP2PError while it starts
    (bad parameters, a missing file, a port taken) is one fatal line and status 1, no traceback.
    The node is destroyed (each node releases its own resources there) and rclpy shut down.
    exit_process: then leave at once with os._exit: unloading torch/Open3D took seconds (past
    launch's SIGINT window under load), and nothing else is left to clean up; and if the teardown
    itself takes more than `exit_grace_s`, leave without it (one line on stderr), same status.
    """
    rclpy.init(args=args)
    node = None
    status = 1  # until the node ends the way it should (an unexpected exception keeps it)
    try:
        node = make_node()
        executor = SingleThreadedExecutor()  # callbacks are short: heavy work runs on the node's own thread
        executor.add_node(node)
        executor.spin()
        status = 0
    except (KeyboardInterrupt, ExternalShutdownException):
        status = 0
    except (_rclpy.RCLError, RuntimeError):
        if rclpy.ok():
            raise
        # SIGINT/SIGTERM shut the context down while the executor was building its wait set (RCLError) or taking
        # a message (pybind11's RuntimeError "Unable to convert call argument", seen under a 10^6 Hz flood)
        status = 0
    except LiverP2PError as exc:
        get_logger(name).fatal(str(exc))
    except ParameterException as exc:  # `-p units:=5` for a string parameter: one line, not rclpy's traceback
        get_logger(name).fatal(str(exc).splitlines()[0] if str(exc) else type(exc).__name__)
    finally:
        if exit_process:
            _exit_after(exit_grace_s, status, name)
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()
    if exit_process:  # rclpy is shut down; flush the logs, skip the interpreter's teardown
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(status)
    return status


def declare_from(node: Node, config_class: type, describe: Callable[[dataclasses.Field], str]) -> list[str]:
    """Declare one ROS parameter per field of a config dataclass (defaults from it: one source of truth),
    described by `describe(field)`; returns their names. A managed node declares in its constructor
    and reads in each configure (a parameter can be declared once only)."""
    defaults = config_class()
    for f in dataclasses.fields(config_class):
        # A descriptor per parameter: rclpy writes the name and type into the object it is given.
        # dynamic_typing: `-p max_rate_hz:=2` (an integer) is coerced by the config instead of rejected.
        descriptor = ParameterDescriptor(description=describe(f), dynamic_typing=True)
        node.declare_parameter(f.name, getattr(defaults, f.name), descriptor)
    return [f.name for f in dataclasses.fields(config_class)]


def read_from(node: Node, config_class: type[ConfigT], names: list[str]) -> ConfigT:
    """The config built from the declared parameters' current values (`config_class.from_dict`)."""
    return config_class.from_dict({name: node.get_parameter(name).value for name in names})


def parameters_from(node: Node, config_class: type[ConfigT], describe: Callable[[dataclasses.Field], str]) -> ConfigT:
    """declare_from, then read_from: a plain node's parameters."""
    return read_from(node, config_class, declare_from(node, config_class, describe))


def log_at(logger: Any, level: int, text: str) -> None:
    """Log `text` at the rclpy severity matching the `logging` level (an rclpy RcutilsLogger)."""
    # rclpy binds one severity to each call site: one call per severity, never a shared one
    if level >= logging.ERROR:
        logger.error(text)
    elif level >= logging.WARNING:
        logger.warning(text)
    elif level >= logging.INFO:
        logger.info(text)
    else:
        logger.debug(text)


class RclpyLogHandler(logging.Handler):
    """Sends Python `logging` records to an rclpy logger (and so to /rosout) through `log(level, text)`."""

    def __init__(self, log: Callable[[int, str], None]) -> None:
        super().__init__()
        self._log = log

    def emit(self, record: logging.LogRecord) -> None:
        self._log(record.levelno, self.format(record))
