"""The one exception type a user can cause: printed as one line, exit status 2."""


class UserError(Exception):
    """A mistake in the user's input (file, option, data). The message says what and how to fix it."""
