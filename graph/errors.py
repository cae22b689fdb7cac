"""Errors the engine reports to the operator."""


class UserError(Exception):
    """An operator-facing problem: one line saying what is wrong and how to fix it."""
