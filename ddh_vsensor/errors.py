"""The error every user-facing problem raises: the CLI prints it and exits 2, no traceback."""


class UserError(Exception):
    """Bad input from the person running the tool: a file, an option, a setting."""
