"""``python -m retrotouch.nodes ...`` is the ``retrotouch`` command."""
from .app import main

main()
