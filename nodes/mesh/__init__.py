"""Mesh ingest (paper section 4): load, scale, repair, remesh, topology check, export."""
