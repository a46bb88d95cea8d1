"""The one exception base of the onboard package; entry points turn these into one line + exit code."""


class IrtrackError(Exception):
    """Base of every error irtrack raises on purpose (bad input, bad config, unobservable...)."""


class InputError(IrtrackError, ValueError):
    """Input data (file, message, payload) is malformed; the message names where."""


class ConfigError(IrtrackError, ValueError):
    """A configuration file or option is invalid; the message names file, field and expectation."""
