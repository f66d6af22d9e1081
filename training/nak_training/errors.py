"""The one exception the training package raises for bad input: it names the file or key at fault."""

from __future__ import annotations


class TrainingInputError(Exception):
    """A dataset, configuration, checkpoint or model directory that cannot be used, and why."""

    def __init__(self, where: object, message: str) -> None:
        super().__init__(f"{where}: {message}")
        self.where = str(where)
        self.message = message
