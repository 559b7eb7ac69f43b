"""The errors polins raises for a user's mistake, as opposed to a bug (docs/faults.md)."""


class UserInputError(ValueError):
    """A mistake in what the user gave polins: a bad option value, file, unit or argument.

    The command line prints it as one line and exits with status 2; any other exception
    is a bug and propagates with its traceback.
    """


class UnknownOptionError(UserInputError, TypeError):
    """An option or keyword polins does not know (a ``TypeError``, as for a bad keyword)."""
