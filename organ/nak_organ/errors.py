"""The one exception the organ package raises for input the user can fix: one line per problem."""

from __future__ import annotations


class OrganInputError(Exception):
    """A surface, option or selection that cannot be used. Each problem names the file or option at
    fault, what is wrong and where (a vertex, a face, an edge, a node), so that the command line can
    print one line per problem and exit with status 2, without a traceback."""

    def __init__(self, problems: list[str]) -> None:
        super().__init__("\n".join(problems))
        self.problems = problems
