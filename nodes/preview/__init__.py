"""Previews of a layout: rendered PNG views and a self-contained interactive HTML view."""
