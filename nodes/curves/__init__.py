"""Curve families (paper section 5): trivial connections, Tx/Rx field lines, crossings."""
