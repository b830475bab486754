"""Errors that are the user's to fix (the CLI prints them as one clear message, without a traceback),
and the one-line form any error takes in a table's cell or a log."""


class UserError(Exception):
    pass


def error_summary(err: BaseException, width: int | None = None) -> str:
    """An error in one line for a table's cell or a log: its type and the first line of its message (at
    most `width` characters of it)."""
    return f"{type(err).__name__}: {(str(err).splitlines() or [''])[0][:width]}"
