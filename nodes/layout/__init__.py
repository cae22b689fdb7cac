"""Layout optimisation (paper section 6): surface samples, curve selection, pads, the best Rx angle, the sensing map sink."""
