"""The command line's exit codes (CONTRACTS §3) and its one error, below every command that raises it."""

from __future__ import annotations

EXIT_OK = 0
EXIT_DIFFERS = 1  # cvxnav replay: the outputs did not reproduce
EXIT_BAD_INPUT = 2
EXIT_NO_PATH = 3
EXIT_TIMEOUT_OR_COLLISION = 4
EXIT_INTERRUPTED = 130  # stopped by SIGINT or SIGTERM (128 + SIGINT, as a shell reports Ctrl-C)
EXIT_BY_STATUS = {"reached": EXIT_OK, "no_path": EXIT_NO_PATH, "timeout": EXIT_TIMEOUT_OR_COLLISION,
                  "collision": EXIT_TIMEOUT_OR_COLLISION,
                  "interrupted": EXIT_INTERRUPTED}  # a run's outcome (run.json's status)


class CliError(Exception):
    """Bad input: printed as one line, exit code 2."""
