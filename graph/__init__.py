"""retrotouch.graph: the cached node-graph dataflow engine."""
