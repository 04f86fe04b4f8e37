"""The errors a command line reports in one line (exit status 2, no traceback: :mod:`torchrl_bail.cli`).

A leaf module: it imports nothing, so every layer (the batch format in :mod:`torchrl_bail.data` included) raises
these without importing the layer that reports them, and the command-line front knows them all up front.

Examples:
    >>> str(ConfigError("algo.selection.percentile", 1.5, "a fraction in (0, 1]"))
    'config key algo.selection.percentile = 1.5: expected a fraction in (0, 1]'
"""

from __future__ import annotations

from typing import Any

__all__ = ["BatchValidationError", "CommandLineError", "ConfigError", "ResumeError", "USER_ERRORS"]


class ConfigError(ValueError):
    """A configuration value is missing or out of range; the message names the key and what was expected."""

    def __init__(self, key: str, value: Any, expected: str):
        self.key, self.value, self.expected = key, value, expected
        super().__init__(f"config key {key} = {value!r}: expected {expected}")

    def under(self, prefix: str) -> ConfigError:
        """The same error with the key ``<prefix>.<key>``."""
        return ConfigError(f"{prefix}.{self.key}" if prefix else self.key, self.value, self.expected)


class CommandLineError(ValueError):
    """The command line itself cannot be composed into a config."""


class ResumeError(ValueError):
    """The run directory cannot be continued by this command (other config, in use, no checkpoint)."""


class BatchValidationError(ValueError):
    """A batch (in memory or on disk) breaks the format; the message names the file, the key, the expectation."""


#: what the command-line front reports as one line (with Hydra's and OmegaConf's own errors and a missing file)
USER_ERRORS = (ConfigError, CommandLineError, ResumeError, BatchValidationError, FileNotFoundError)
