"""Errors that are the user's to fix: printed as one clear message, exit code 2, no traceback."""

from __future__ import annotations


class UserError(Exception):
    """A mistake in the user's input (matrix file, model, dataset, command line)."""

    exit_code = 2


class StepError(UserError):
    """A step every cell depends on failed (e.g. building the dataset): reported without traceback, exit 1."""

    exit_code = 1


class MatrixError(UserError):
    """One or more problems in a matrix file, each already located (file:line: key: message)."""

    def __init__(self, problems: list[str]):
        self.problems = problems
        super().__init__("\n".join(problems))
