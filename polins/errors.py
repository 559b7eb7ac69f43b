"""The errors polins raises for a user's mistake, as opposed to a bug (docs/faults.md)."""


class UserInputError(ValueError):
    """A mistake in what the user gave polins: a bad option, file, unit or argument.

    The command line prints it as one line and exits with status 2; any other exception
    is a bug and propagates with its traceback.
    """
