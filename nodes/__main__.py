"""``python -m retrotouch.nodes ...`` is the ``retrotouch`` command."""
from ..graph import interrupts

interrupts.install()  # first thing: a Ctrl-C during the imports below is one clean line too
try:
    from .app import main
except interrupts.Interrupted as exc:
    interrupts.exit_interrupted("retrotouch", exc)

main()
