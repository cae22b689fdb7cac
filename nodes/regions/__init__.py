"""Surface regions: the resting base (non-sensing), the sensing region and what a finger can touch."""
