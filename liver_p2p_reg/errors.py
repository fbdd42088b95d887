"""Exceptions whose message is a one-line, user-facing explanation."""


class LiverP2PError(Exception):
    """Base class: the message is shown to users as a single line (no traceback)."""


class InputError(LiverP2PError):
    """Bad user input: missing/unreadable file, empty or NaN-only cloud, bad option."""


class RegistrationError(LiverP2PError):
    """The registration could not produce a trustworthy transform."""


class WeightsError(LiverP2PError):
    """Model weights are missing, corrupt or incompatible."""
