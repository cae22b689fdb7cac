"""``python -m retrotouch.nodes ...`` is the ``retrotouch`` command."""
from ..graph import interrupts

interrupts.install()  # first thing: a Ctrl-C during the imports below is one clean line too
try:  # the imports and every moment until the command line's own handling is in place
    from .app import main

    main()
except interrupts.Interrupted as exc:
    interrupts.exit_interrupted("retrotouch", exc)
