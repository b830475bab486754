"""Errors that are the user's to fix; the CLI prints them as one clear message, without a traceback."""


class UserError(Exception):
    pass
