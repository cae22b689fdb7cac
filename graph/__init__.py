"""The cached node-graph dataflow engine (application-independent: see :mod:`.app`)."""
