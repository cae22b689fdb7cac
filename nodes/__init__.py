"""retrotouch.nodes: the pipeline steps. Every module here that defines ``@node`` functions is
discovered by the engine (no registration list to edit)."""
