"""Fabrication (paper section 7.1): unfolded traces, outlines, nesting, cut sheets, assembly guide."""
