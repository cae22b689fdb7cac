"""Surface regions: the resting base (non-sensing) and the sensing region."""
