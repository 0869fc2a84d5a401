"""Exceptions of aft_ftm: one root, specific subclasses."""


class AftError(Exception):
    """Root of every error raised by aft_ftm."""


class ConfigError(AftError):
    """A parameter or configuration value is invalid; the message names it and its value."""


class RebindError(AftError):
    """A rebind request was refused; the node's bindings are unchanged."""


class StateError(AftError):
    """A server state could not be captured or applied; the server's state is unchanged."""


class RoleError(AftError):
    """A replica role change that the state machine does not allow."""
