"""The one exception type that means "the user's input is unusable" (exit code 2)."""


class InputError(Exception):
    """Unusable input: a file, a flag or a configuration value.

    The command line turns it into a one-line reason on stderr and exit code 2.

    Parameters
    ----------
    source : str
        What is wrong: a file path, a flag (``--levels``) or a config key.
    problem : str
        What is wrong with it and, where possible, how to fix it.
    """

    def __init__(self, source, problem):
        self.source = str(source)
        self.problem = problem
        super().__init__(f"{self.source}: {problem}")


def first_line(error):
    """Return the first line of an exception's text, or its type's name when it has none.

    For messages that quote a library: torch's and KLayout's run to a page.
    """
    lines = str(error).strip().splitlines()
    return lines[0] if lines else type(error).__name__
