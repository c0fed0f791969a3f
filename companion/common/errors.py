"""The one exception type for mistakes a user can make (bad file, config, model, argument).

Command-line fronts catch it and print its message as one line with a non-zero exit,
so users never see a traceback for their own input.
"""


class UserError(Exception):
    """Bad input from the user; the message names what was wrong."""
