"""Shared data: the in-memory types that flow between stages and the file formats they are written in."""
