"""retrotouch.nodes: the application. One sub-package per pipeline stage (``mesh``, ``regions``,
``curves``, ``layout``, ``fab``, ``projection``, ``preview``, ``sensing``) plus the shared ``data``
and ``geometry`` packages; see ARCHITECTURE.md. Every module that defines ``@node`` functions is
discovered by the engine (no registration list to edit); :mod:`.app` is the entry point."""
