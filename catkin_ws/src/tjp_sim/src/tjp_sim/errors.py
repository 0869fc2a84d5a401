"""Exceptions of tjp_sim: one root, specific subclasses."""


class TjpError(Exception):
    """Root of every error raised by tjp_sim."""


class TjpConfigError(TjpError):
    """A configuration, scenario or state value is invalid; the message names it."""
