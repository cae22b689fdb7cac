"""Errors the engine reports to the operator."""


class UserError(Exception):
    """An operator-facing problem: one line saying what is wrong and how to fix it."""


class NodeFailed(Exception):
    """A node raised an unexpected exception: one-line summary naming the node and the log file
    holding the traceback (the engine exits with code 1)."""
