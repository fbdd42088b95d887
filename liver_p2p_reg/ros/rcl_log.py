"""Python logging levels onto an rclpy logger, one call site per severity."""

from __future__ import annotations

import logging
from typing import Any


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
