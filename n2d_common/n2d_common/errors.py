"""Typed errors of n2d: every failure a user can fix carries one line saying what is wrong and a hint."""


class N2DError(Exception):
    """Base of n2d's user-facing errors: `message` says what is wrong, `hint` how to fix it."""

    def __init__(self, message: str, hint: str = ""):
        super().__init__(message)
        self.message = message
        self.hint = hint

    def __str__(self) -> str:
        return f"{self.message} (hint: {self.hint})" if self.hint else self.message


class ConfigError(N2DError):
    """A configuration file, override or parameter is malformed or out of range."""

    DEFAULT_HINT = "fix the value in the config file, the --set override or the parameter"

    def __init__(self, message: str, hint: str = ""):
        super().__init__(message, hint or self.DEFAULT_HINT)


class ContractError(N2DError):
    """A stage directory is missing, incomplete, of another kind, or would overwrite something."""


class DeviceError(N2DError):
    """Hardware (or its simulator) failed: serial port, servo, camera."""


class Cancelled(N2DError):
    """A long job was cancelled by the user; what it finished is kept and a re-run resumes."""
