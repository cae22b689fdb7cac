"""Shared geometry over ``(V, F)`` arrays (millimetres, faces CCW seen from outside)."""
