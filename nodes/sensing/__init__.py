"""Touch sensing at runtime (paper section 8): Muca serial link, virtual board, touch processing, gestures, live view, evaluation, ``retrotouch sense``."""
