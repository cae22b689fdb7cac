"""Projection-guided assembly (paper section 7.3): layout textures, projector-camera calibration, rendering, depth tracking, ``retrotouch project*`` commands."""
